"""Benchmark: a sweep of R runs against the same R runs one by one, in one process.

For every case (method x range model) and R in `--runs` (default 1, 4, 16): R single warm fast
runs (each `pgp.prepare` + `pgp.run_chunked` + the sweep's metric reduction: what `run_pgp` does
for one calibration, the windowed fast path), then one sweep of the same R runs
(`sweep.build_groups` + `sweep.execute`, `--execution`, default "auto": "sequential" on CPU).
Runs differ in sigma_r (R values between 0.2 and 0.6 m). Everything is compiled before timing (one
warm-up run of each path). The two are timed alternately `--repeats` times (best of each: on a
shared machine the load changes between timings). Prints one JSON line per (case, R): single_s
(the R runs, summed), sweep_s, per-run seconds of both, ratio = sweep_s / single_s,
metrics_equal (every metric of every run identical, bit for bit), single_cpu_s, sweep_cpu_s and
cpu_ratio (the same with the process's CPU time, all threads: robust to other jobs on a shared
machine, where wall times of the same work vary by 2x), loadavg (`os.getloadavg()` when the row
finished), device.

Data: `data/torgau.h5` (12 nodes, the simulated torgau scenario) when present, else
`simulate("torgau", 0)`; its first `--epochs` epochs, `--cell` m cells, float32 (as the CLI).

Usage: python benchmarks/sweep_throughput.py [--epochs 100] [--cell 0.5] [--runs 1,4,16]
       [--cases pgp:gaussian,pgp:mixture,parametric:gaussian,parametric:mixture]
       [--execution auto|sequential|vmap] [--repeats 1]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def dataset():
    from jaxcal.sim.mesh import simulate

    path = ROOT / "data" / "torgau.h5"
    if path.exists():
        from jaxcal.io import hdf5

        return hdf5.read(path), "conf1"
    return simulate("torgau", 0), "conf1"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=100)
    ap.add_argument("--cell", type=float, default=0.5)
    ap.add_argument("--runs", default="1,4,16")
    ap.add_argument("--cases", default="pgp:gaussian,pgp:mixture,parametric:gaussian,parametric:mixture")
    ap.add_argument("--execution", default="auto", choices=("auto", "sequential", "vmap"))
    ap.add_argument("--batch-size", type=int, default=16, help="runs per device in one batch")
    ap.add_argument("--repeats", type=int, default=1, help="alternated timings, best of each")
    a = ap.parse_args()

    import jax
    import numpy as np

    from jaxcal import sweep as S
    from jaxcal.mesh import pgp
    from jaxcal.params import with_overrides
    from jaxcal.tune import grid_span_m, truth_in_filter_order, window

    full, config = dataset()
    ds = window(full, a.epochs)
    dev = jax.devices()[0]
    for case in a.cases.split(","):
        method, range_model = case.split(":")
        fixed = {"cell_m": a.cell, "range_model": range_model}

        def single(sigma_r, fixed=fixed, method=method):
            """One calibration's compute on the fast path, reduced to the sweep's metrics."""
            p = with_overrides(pgp.PGPParams(), {**fixed, "sigma_r": float(sigma_r)})
            cfg, prm, inp, lp0, order = pgp.prepare(ds, p, config, method)
            _, out = pgp.run_chunked(cfg, prm, inp, lp0)
            truth = jax.numpy.asarray(truth_in_filter_order(ds, config, order), lp0.dtype)
            m = S._reduce_jit(out, prm, truth, grid_span_m(cfg))
            return {k: float(v) for k, v in m.items()}

        def sweep(values, fixed=fixed, method=method):
            spec = S.parse_spec(
                {
                    "method": method,
                    "batch_size": a.batch_size,
                    "execution": a.execution,
                    "params": fixed,
                    "grid": {"sigma_r": [float(v) for v in values]},
                    "scenarios": [{"file": "torgau", "config": config}],
                }
            )
            pl = S.plan(spec)
            groups, group_of = S.build_groups([(ds, config)], spec)
            got = {k: np.full(pl.n_runs, np.nan) for k in S.METRICS}
            for idx, vals in S.execute(spec, pl, groups, group_of, np.zeros(pl.n_runs, bool)):
                for k, v in vals.items():
                    got[k][idx] = v
            return got

        t0 = time.perf_counter()
        single(0.3)  # compile both paths before timing
        sweep([0.3])
        compile_s = time.perf_counter() - t0
        for r in (int(x) for x in a.runs.split(",")):
            values = np.linspace(0.2, 0.6, r) if r > 1 else np.asarray([0.3])
            single_s = sweep_s = single_cpu = sweep_cpu = float("inf")
            for _ in range(a.repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                one = [single(v) for v in values]
                single_s = min(single_s, time.perf_counter() - t0)
                single_cpu = min(single_cpu, time.process_time() - c0)
                t0, c0 = time.perf_counter(), time.process_time()
                got = sweep(values)
                sweep_s = min(sweep_s, time.perf_counter() - t0)
                sweep_cpu = min(sweep_cpu, time.process_time() - c0)
            equal = all(
                np.float64(got[k][i]).tobytes() == np.float64(one[i][k]).tobytes()
                or (np.isnan(got[k][i]) and np.isnan(one[i][k]))
                for i in range(r)
                for k in S.METRICS
            )
            print(
                json.dumps(
                    {
                        "bench": "sweep_throughput",
                        "method": method,
                        "range_model": range_model,
                        "runs": r,
                        "epochs": ds.n_epochs,
                        "nodes": ds.n_nodes,
                        "cell_m": a.cell,
                        "execution": S.resolve_execution(a.execution),
                        "compile_s": round(compile_s, 2),
                        "single_s": round(single_s, 3),
                        "sweep_s": round(sweep_s, 3),
                        "single_per_run_s": round(single_s / r, 3),
                        "sweep_per_run_s": round(sweep_s / r, 3),
                        "ratio": round(sweep_s / single_s, 3),
                        "single_cpu_s": round(single_cpu, 3),
                        "sweep_cpu_s": round(sweep_cpu, 3),
                        "cpu_ratio": round(sweep_cpu / single_cpu, 3),
                        "metrics_equal": bool(equal),
                        "repeats": a.repeats,
                        "loadavg": [round(x, 2) for x in os.getloadavg()],
                        "cpus": os.cpu_count(),
                        "device": f"{dev.platform}:{dev.device_kind}",
                    }
                ),
                flush=True,
            )


if __name__ == "__main__":
    main()
