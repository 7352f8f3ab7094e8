"""Issue #19 item 3: `gp` run time on 10 anchors x ~1e5 ranges, and accuracy against the training-set
size (JSON lines). `--model path` or `space`: the path or spatial GP on every range (`gp_path`, `gp_space`; n_train
is then unused: give one).

    python benchmarks/gp_speed.py [--rate 150] [--n 100 300 1000] [--seed 0] [--block 0] [--model path|space]
        [--methods nls gp]

The simulated campus (10 anchors, NLOS behind buildings) ranged at `--rate` Hz per anchor (150 Hz:
about 1e5 ranges). Per n_train: `gp` cold (JIT compilation included) and warm seconds, wall and
process CPU (CPU is the figure to compare on a shared machine), mean anchor error; `nls` alone for
reference, first, in the same process (so gp's cold call reuses what nls compiled; `--methods gp`: gp alone, cold
in a fresh process, as the command line runs it without the compile cache). On a shared CPU set
XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1".
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from jaxcal.methods import calibrate
from jaxcal.sim.trajectory import simulate


def timed(ds, method, params):
    """(result, {cold_s, warm_s, cold_cpu_s, warm_cpu_s}, mean error): wall and process CPU seconds of
    a first (JIT compilation included) and a second call."""
    t0, c0 = time.perf_counter(), time.process_time()
    res = calibrate(ds, method, params)
    t1, c1 = time.perf_counter(), time.process_time()
    calibrate(ds, method, params)
    t2, c2 = time.perf_counter(), time.process_time()
    e = res.position - ds.anchor_truth
    ok = np.isfinite(e).all(axis=1)
    secs = {"cold_s": t1 - t0, "warm_s": t2 - t1, "cold_cpu_s": c1 - c0, "warm_cpu_s": c2 - c1}
    return res, {k: round(v, 2) for k, v in secs.items()}, float(np.linalg.norm(e[ok], axis=1).mean())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rate", type=float, default=150.0)
    ap.add_argument("--n", nargs="*", type=int, default=[100, 300, 1000])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--block", type=int, default=0)
    ap.add_argument("--model", default="subsample", help="gp model: subsample, path, space or excess")
    ap.add_argument(
        "--methods",
        nargs="+",
        choices=("nls", "gp"),
        default=["nls", "gp"],
        help="nls first, then gp (either may be left out)",
    )
    a = ap.parse_args()
    ds = simulate("campus", seed=a.seed, range_rate_hz=a.rate)
    base = {"dataset": f"campus seed={a.seed} rate={a.rate:g}", "ranges": int(ds.range.size)}
    if "nls" in a.methods:
        _, secs, err = timed(ds, "nls", {})
        print(
            json.dumps({**base, "method": "nls", **secs, "mean_error_m": err, "load1": round(os.getloadavg()[0], 2)}),
            flush=True,
        )
    for n in a.n if "gp" in a.methods else []:
        p = {"n_train": n, "block": a.block, "model": a.model}
        _, secs, err = timed(ds, "gp", p)
        print(
            json.dumps(
                {
                    **base,
                    "method": "gp",
                    **p,
                    **secs,
                    "mean_error_m": err,
                    "load1": round(os.getloadavg()[0], 2),
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
