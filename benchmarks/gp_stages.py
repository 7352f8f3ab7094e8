"""Where a trajectory calibration's time goes, by stage, cold and warm (issue #19 item 3; JSON lines).

    python benchmarks/gp_stages.py [--rate 150] [--seed 0] [--methods nls gp] [--set model=excess ...]

The simulated campus (10 anchors) ranged at `--rate` Hz per anchor; each method in `--methods` is called twice
in this one process (cold: JIT compilation included; warm), in the order given. Every stage function (the list
`STAGES`) is wrapped: wall seconds with `jax.block_until_ready` on its output, and the XLA programs compiled
inside it (`jax_log_compiles`: count and backend-compile seconds, and tracing + lowering seconds). Nested stages
count in their parent too. One line per (method, call, stage), then one per call with the total wall and process
CPU seconds. Run with `JAXCAL_CACHE_DIR` unset (the library never enables the persistent cache; the CLI does) and
XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" on a shared CPU.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import re
import sys
import time
from collections import defaultdict

import jax

from jaxcal.methods import calibrate
from jaxcal.sim.trajectory import simulate

# (module, function): what each stage is; nested ones (e.g. nls.solve_all_checked inside nls.prepare_offset) count
# in both
STAGES = [
    ("jaxcal.trajectory.nls", "prepare_offset"),
    ("jaxcal.trajectory.nls", "solve_all_checked"),
    ("jaxcal.trajectory.poses", "estimate_offset_fit"),
    ("jaxcal.trajectory.poses", "prepare_poses"),
    ("jaxcal.trajectory.nls", "cell_covariances"),
    ("jaxcal.trajectory.gp_excess", "fit_excess_all"),
    ("jaxcal.trajectory.drift", "drift_for_covariance"),
    ("jaxcal.trajectory.pose_error", "pose_error_covariances"),
    ("jaxcal.trajectory.common", "finish"),
    ("jaxcal.trajectory.mirror", "compare_sides"),
    ("jaxcal.trajectory.mirror", "_compare_all"),
    ("jaxcal.trajectory.mirror", "_profile_all"),
]

_active: list[str] = []
_stats: dict = defaultdict(lambda: defaultdict(float))
_COMPILE = re.compile(r"Finished XLA compilation of (.*) in ([0-9.]+) sec")
_TRACE = re.compile(r"Finished (tracing|jaxpr to MLIR).* in ([0-9.]+) sec")


class _CompileLog(logging.Handler):
    """Adds the compile and trace seconds JAX logs (`jax_log_compiles`) to every active stage."""

    def emit(self, record):
        msg = record.getMessage()
        m = _COMPILE.search(msg)
        for stage in _active + ["(call)"]:
            if m:
                _stats[stage]["compiles"] += 1
                _stats[stage]["compile_s"] += float(m.group(2))
                progs = _stats[stage].setdefault("programs", {})
                progs[m.group(1)] = round(progs.get(m.group(1), 0.0) + float(m.group(2)), 2)
            else:
                t = _TRACE.search(msg)
                if t:
                    _stats[stage]["trace_s"] += float(t.group(2))


def _wrap(name, fn):
    def wrapped(*args, **kwargs):
        _active.append(name)
        t0 = time.perf_counter()
        try:
            out = fn(*args, **kwargs)
            jax.block_until_ready(jax.tree_util.tree_leaves(out, is_leaf=lambda x: x is None))
            return out
        finally:
            _stats[name]["wall_s"] += time.perf_counter() - t0
            _stats[name]["calls"] += 1
            _active.pop()

    wrapped.__wrapped__ = fn
    return wrapped


def _install():
    """Replace every stage function by its timed wrapper wherever a jaxcal module holds it by name."""
    for mod_name, fn_name in STAGES:
        mod = importlib.import_module(mod_name)
        fn = getattr(mod, fn_name)
        wrapped = _wrap(f"{mod_name.rsplit('.', 1)[-1]}.{fn_name}", fn)
        for other in list(sys.modules.values()):
            if getattr(other, "__name__", "").startswith("jaxcal") and getattr(other, fn_name, None) is fn:
                setattr(other, fn_name, wrapped)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rate", type=float, default=150.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", nargs="*", default=["nls", "gp"])
    ap.add_argument("--set", nargs="*", default=[], help="gp parameters, key=value")
    a = ap.parse_args()
    for m in ("jaxcal.trajectory.gp", "jaxcal.trajectory.gp_path", "jaxcal.trajectory.gp_excess"):
        importlib.import_module(m)
    jax.config.update("jax_log_compiles", True)
    handler = _CompileLog()
    logging.getLogger("jax").addHandler(handler)
    logging.getLogger("jax").propagate = False  # the compile lines are counted, not printed
    _install()
    ds = simulate("campus", seed=a.seed, range_rate_hz=a.rate)
    gp_p = dict(kv.split("=", 1) for kv in a.set)
    for method in a.methods:
        for call in ("cold", "warm"):
            _stats.clear()
            t0, c0 = time.perf_counter(), time.process_time()
            calibrate(ds, method, gp_p if method == "gp" else {})
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            base = {"method": method, "call": call, "ranges": int(ds.range.size)}
            for stage, s in _stats.items():
                row = {k: (round(v, 2) if isinstance(v, float) else v) for k, v in s.items()}
                print(json.dumps({**base, "stage": stage, **row}), flush=True)
            print(
                json.dumps(
                    {
                        **base,
                        "stage": "total",
                        "wall_s": round(wall, 2),
                        "cpu_s": round(cpu, 2),
                        "load1": round(os.getloadavg()[0], 2),
                    }
                ),
                flush=True,
            )


if __name__ == "__main__":
    main()
