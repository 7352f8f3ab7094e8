"""Benchmark: sweep throughput (runs per second) of the vmapped, sharded filter on 1, 2, 4 devices.

Each device count runs in its own subprocess, because virtual CPU devices
(`XLA_FLAGS=--xla_force_host_platform_device_count=D`) must be set before JAX initialises; on a
machine with accelerators, `--real` uses the first D real devices instead. Per device count: one
JSON line with the device kind, the batch (runs per device x devices), the compile time (first
batch, including compilation) and the best of `--repeats` timed batches after it
(`jax.block_until_ready`), as runs per second. The workload: simulated `small` (6 nodes) or
`torgau` (12 nodes) scenario, first `--epochs` epochs, `--cell` m cells, dense likelihood, sigma_r
varying over the batch. Note: virtual CPU devices share the host's cores, so on a 2-core machine
more devices cannot be faster; the figure shows the overhead of sharding, not a speed-up.

Usage: python benchmarks/sweep_throughput.py [--scenario small] [--epochs 50] [--cell 2.0]
       [--per-device 4] [--devices 1,2,4] [--repeats 3] [--real]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time


def worker(a) -> None:
    import jax
    import numpy as np

    from jaxcal import sweep as S
    from jaxcal.sim.mesh import simulate

    devs = jax.devices()[: a.n]
    spec = S.parse_spec(
        {
            "epochs": a.epochs,
            "batch_size": a.per_device,
            "params": {
                "cell_m": a.cell,
                "max_hyp": 4,
                "top_k": 8,
                "min_refs": 2,
                "likelihood": "dense",
            },
            "grid": {"sigma_r": list(np.linspace(0.2, 2.0, a.per_device * a.n * (a.repeats + 1)))},
            "scenarios": [{"simulate": a.scenario, "config": "conf1", "seeds": [0]}],
        }
    )
    pl = S.plan(spec)
    groups, group_of = S.build_groups([(simulate(a.scenario, 0), "conf1")], spec)
    it = S.execute(spec, pl, groups, group_of, np.zeros(pl.n_runs, bool), devices=devs)
    t0 = time.perf_counter()
    idx, _ = next(it)  # compile + first batch (metrics are host arrays: the batch has finished)
    first = time.perf_counter() - t0
    times = []
    for _ in range(a.repeats):
        t0 = time.perf_counter()
        idx, _ = next(it)
        times.append(time.perf_counter() - t0)
    best = min(times)
    print(
        json.dumps(
            {
                "bench": "sweep_throughput",
                "devices": len(devs),
                "device_kind": devs[0].device_kind,
                "platform": devs[0].platform,
                "scenario": a.scenario,
                "epochs": a.epochs,
                "cell_m": a.cell,
                "grid_side": groups[0].cfg.grid.n_side,
                "batch": int(idx.size),
                "per_device": a.per_device,
                "first_batch_s": first,
                "best_batch_s": best,
                "runs_per_s": idx.size / best,
                "repeats": a.repeats,
                "dtype": str(np.asarray(groups[0].base.sigma_r).dtype),
            }
        ),
        flush=True,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="small")
    ap.add_argument("--epochs", type=int, default=50)
    ap.add_argument("--cell", type=float, default=2.0)
    ap.add_argument("--per-device", type=int, default=4)
    ap.add_argument("--devices", default="1,2,4")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--real", action="store_true", help="use real devices (no virtual CPU devices)")
    ap.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker is not None:
        a.n = a.worker
        worker(a)
        return
    for n in (int(x) for x in a.devices.split(",")):
        env = dict(os.environ)
        if not a.real:
            env["JAX_PLATFORMS"] = "cpu"
            env["XLA_FLAGS"] = (
                env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={n}"
            ).strip()
        args = [
            sys.executable,
            __file__,
            "--worker",
            str(n),
            "--scenario",
            a.scenario,
            "--epochs",
            str(a.epochs),
            "--cell",
            str(a.cell),
            "--per-device",
            str(a.per_device),
            "--repeats",
            str(a.repeats),
        ]
        proc = subprocess.run(args, env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            print(
                json.dumps(
                    {"bench": "sweep_throughput", "devices": n, "error": proc.stderr.strip()[-300:]}
                )
            )
        else:
            sys.stdout.write(proc.stdout)
        sys.stdout.flush()


if __name__ == "__main__":
    main()
