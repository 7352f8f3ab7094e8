"""Benchmark: sweep throughput (runs/s) against batch size, for accelerators.

One command on a GPU machine (the defaults are the figures the docs ask for):

    python benchmarks/sweep_batching.py

For each cell size in `--cells` (default 0.5, 0.25 m) and batch size B in `--batches` (default
1, 4, 16, 64, 256): one sweep batch of B runs (sigma_r varying over the batch) of the 12-node
torgau dataset (`data/torgau.h5`, else `simulate("torgau", 0)`), first `--epochs` epochs (default
2000), with `--execution` (default "vmap": the accelerator execution of `jaxcal.sweep`, one jitted
vmapped filter per batch). The first batch compiles (compile_s, measured as first call minus
best; the lockstep driver's window program compiles at the first batch that reaches a windowed
step, so keep `--repeats` >= 2); then the best of `--repeats` batches. One JSON line per (cell, B):
runs_per_s = B / best_batch_s, and for reference `single_runs_per_s`: one warm single fast run
(`pgp.run_chunked`, as `run_pgp`; the "sequential" execution's per-run cost) measured once per
cell size in the same process. A batch that fails (e.g. out of device memory) prints a line with
"error" and the sweep goes on with the next size.

On CPU run it only at tiny sizes to check it works, e.g.

    JAX_PLATFORMS=cpu python benchmarks/sweep_batching.py --epochs 20 --cells 2.0 --batches 1,2
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=2000)
    ap.add_argument("--cells", default="0.5,0.25")
    ap.add_argument("--batches", default="1,4,16,64,256")
    ap.add_argument("--method", default="pgp", choices=("pgp", "parametric"))
    ap.add_argument("--range-model", default="gaussian", choices=("gaussian", "mixture"))
    ap.add_argument("--execution", default="vmap", choices=("auto", "sequential", "vmap"))
    ap.add_argument("--repeats", type=int, default=2)
    a = ap.parse_args()

    import jax
    import numpy as np

    from jaxcal import sweep as S
    from jaxcal.mesh import pgp
    from jaxcal.params import with_overrides
    from jaxcal.sim.mesh import simulate
    from jaxcal.tune import window

    path = ROOT / "data" / "torgau.h5"
    if path.exists():
        from jaxcal.io import hdf5

        full = hdf5.read(path)
    else:
        full = simulate("torgau", 0)
    ds, config = window(full, a.epochs), "conf1"
    dev = jax.devices()[0]
    for cell in (float(c) for c in a.cells.split(",")):
        fixed = {"cell_m": cell, "range_model": a.range_model}
        p = with_overrides(pgp.PGPParams(), fixed)
        cfg, prm, inp, lp0, _ = pgp.prepare(ds, p, config, a.method)
        jax.block_until_ready(pgp.run_chunked(cfg, prm, inp, lp0))  # compile
        t0 = time.perf_counter()
        jax.block_until_ready(pgp.run_chunked(cfg, prm, inp, lp0))
        single_s = time.perf_counter() - t0
        for b in (int(x) for x in a.batches.split(",")):
            row = {
                "bench": "sweep_batching",
                "method": a.method,
                "range_model": a.range_model,
                "execution": S.resolve_execution(a.execution, dev.platform),
                "cell_m": cell,
                "grid_side": cfg.grid.n_side,
                "nodes": ds.n_nodes,
                "epochs": ds.n_epochs,
                "batch": b,
                "single_runs_per_s": round(1.0 / single_s, 4),
                "device": f"{dev.platform}:{dev.device_kind}",
                "devices": jax.device_count(),
            }
            try:
                spec = S.parse_spec(
                    {
                        "method": a.method,
                        "batch_size": b,
                        "execution": a.execution,
                        "params": fixed,
                        # (repeats + 1) batches of b runs each
                        "grid": {"sigma_r": list(np.linspace(0.2, 0.6, b * (a.repeats + 1)))},
                        "scenarios": [{"file": "torgau", "config": config}],
                    }
                )
                pl = S.plan(spec)
                groups, group_of = S.build_groups([(ds, config)], spec)
                it = S.execute(spec, pl, groups, group_of, np.zeros(pl.n_runs, bool), devices=[dev])
                t0 = time.perf_counter()
                next(it)  # compile + first batch (metrics are host arrays: it has finished)
                first = time.perf_counter() - t0
                times = []
                for _ in range(a.repeats):
                    t0 = time.perf_counter()
                    next(it)
                    times.append(time.perf_counter() - t0)
                best = min(times) if times else first
                row.update(
                    compile_s=round(first - best, 2),
                    best_batch_s=round(best, 3),
                    runs_per_s=round(b / best, 4),
                    speedup_vs_single=round(b / best * single_s, 3),
                )
            except Exception as e:  # noqa: BLE001 - report (e.g. out of memory) and go on
                row["error"] = f"{type(e).__name__}: {str(e)[:300]}"
            row["loadavg"] = [round(x, 2) for x in os.getloadavg()]
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
