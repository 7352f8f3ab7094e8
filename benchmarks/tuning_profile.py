"""Where a default `jaxcal tune` run spends its time: one line per phase, wall and CPU seconds.

Runs what `jaxcal tune FILE --method pgp --config conf1` runs (evidence objective, gradient phase
on the first 200 epochs at 1 m cells, 12 BFGS steps at most, the guard on calibrate's run) in one
process, with the command line's compile cache, and prints the cumulative wall time, CPU time
(`time.process_time`, every thread) and JAX's tracing / lowering / XLA-compile seconds (from
`jax.monitoring`) after loading, after every BFGS step and after each of the guard's filter runs.

    JAXCAL_CACHE_DIR=DIR PYTHONPATH=src python benchmarks/tuning_profile.py [data/torgau.h5]
"""

from __future__ import annotations

import collections
import json
import sys
import time

import jax
import jax.monitoring

from jaxcal import compile_cache
from jaxcal import tune as T
from jaxcal import tune_eval as E
from jaxcal.commands._common import load, resolve_config

EVENTS = {
    "trace": "/jax/core/compile/jaxpr_trace_duration",
    "lower": "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "compile": "/jax/core/compile/backend_compile_duration",
    "cache load": "/jax/compilation_cache/cache_retrieval_time_sec",
}


def main() -> None:
    compile_cache.enable()
    t0, c0 = time.perf_counter(), time.process_time()
    seconds: dict[str, float] = collections.defaultdict(float)
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, dur, **kw: seconds.__setitem__(name, seconds[name] + dur)
    )

    def mark(what: str) -> None:
        jax_s = " ".join(f"{k} {seconds[v]:6.1f}" for k, v in EVENTS.items())
        print(
            f"{what:28s} wall {time.perf_counter() - t0:7.1f} cpu {time.process_time() - c0:7.1f} | {jax_s}",
            flush=True,
        )

    hard_run = E.hard_run

    def timed_run(*a, **k):
        out = hard_run(*a, **k)
        jax.block_until_ready(out[2].estimate)
        mark("guard: held-out fold run" if k.get("z_mask") is not None else "guard: calibrate's run")
        return out

    E.hard_run = timed_run
    ds = load(sys.argv[1] if len(sys.argv) > 1 else "data/torgau.h5", ("mesh",))
    ds, config = resolve_config(ds, "conf1")
    mark("loaded")
    res = T.tune(
        ds,
        {},
        config,
        objective_name="evidence",
        epochs=200,
        cell_m=1.0,
        on_step=lambda k, v: mark(f"step {k} ({v:.5f})"),
    )
    mark("done")
    print(
        json.dumps(
            {
                "accepted": res.accepted,
                "steps": res.steps,
                "message": res.message,
                "tuned": res.tuned,
                "hard_before": res.hard_before,
                "hard_after": res.hard_after,
                "guard_gain_t": res.settings["guard_gain_t"],
                "seconds": res.seconds,
            }
        )
    )


if __name__ == "__main__":
    main()
