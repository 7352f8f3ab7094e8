"""Trajectory anchor calibration: mean anchor error and run time per method (JSON lines on stdout).

    python benchmarks/trajectory_calibration.py [FILE.h5 ...] [--campus] [--subsample]

FILE.h5: trajectory files with anchor truth (e.g. written by `jaxcal import hymn|cuhksz|hanyang`).
--campus: the simulated campus scenario without and with odometry drift (0.05 m/sqrt(s)).
--subsample: GP accuracy against the training-set size on campus (quick look; the full measurement
with an nls control on the same subsample is benchmarks/gp_subsampling.py).
Run time includes JIT compilation of the first call of each configuration ("seconds") and is
repeated once warm ("warm_seconds"). On a shared CPU set
XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" (no oversubscription).
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np

from jaxcal.io import hdf5
from jaxcal.methods import calibrate

CONFIGS = [
    ("ls", {}),
    ("nls", {}),
    ("gp", {}),  # the default since issue #19: mean=anchor, nls-seeded and bounded
    ("gp", {"mean": "constant", "target": "range", "nu": 1.5}),
    ("gp", {"mean": "constant", "target": "inv-log", "nu": 5.0 / 3.0}),
    ("gp", {"mean": "constant", "search": "gradient"}),
]


def run(ds, method, params, label):
    t0 = time.perf_counter()
    res = calibrate(ds, method, params)
    t1 = time.perf_counter()
    calibrate(ds, method, params)
    t2 = time.perf_counter()
    truth = ds.anchor_truth
    err = np.linalg.norm(res.position - truth, axis=1)
    ok = np.isfinite(err)
    hz = np.abs(res.position[:, 2] - truth[:, 2])
    h = np.linalg.norm(res.position[:, :2] - truth[:, :2], axis=1)
    print(
        json.dumps(
            {
                "dataset": label,
                "method": method,
                "params": {k: v for k, v in params.items()},
                "mean_error_m": float(err[ok].mean()) if ok.any() else None,
                "median_error_m": float(np.median(err[ok])) if ok.any() else None,
                "mean_horizontal_m": float(h[ok].mean()) if ok.any() else None,
                "mean_vertical_m": float(hz[ok].mean()) if ok.any() else None,
                "estimated": int(ok.sum()),
                "anchors": int(err.size),
                "mean_reported_sd_m": float(np.sqrt(np.trace(res.covariance[ok], axis1=1, axis2=2) / 3).mean())
                if ok.any()
                else None,
                "seconds": round(t1 - t0, 2),
                "warm_seconds": round(t2 - t1, 2),
                "time_offset_s": res.params.get("info_time_offset_s"),
                "device": jax.devices()[0].platform,
            }
        ),
        flush=True,
    )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("files", nargs="*")
    ap.add_argument("--campus", action="store_true")
    ap.add_argument("--subsample", action="store_true")
    ap.add_argument("--offset", action="store_true", help="also run nls with clock-offset estimation")
    a = ap.parse_args()
    for f in a.files:
        ds = hdf5.read(f)
        for m, p in CONFIGS:
            run(ds, m, p, ds.name)
        if a.offset:
            run(ds, "nls", {"estimate_offset": True}, ds.name)
            run(ds, "gp", {"estimate_offset": True}, ds.name)
    if a.campus or a.subsample:
        from jaxcal.sim.trajectory import simulate

        for drift in (0.0, 0.05) if a.campus else ():
            ds = simulate("campus", seed=0, drift=drift)
            for m, p in CONFIGS:
                run(ds, m, p, ds.name)
        if a.subsample:
            ds = simulate("campus", seed=0)
            for n in (100, 200, 400, 800):
                run(ds, "gp", {"n_train": n}, f"{ds.name} n_train={n}")


if __name__ == "__main__":
    main()
