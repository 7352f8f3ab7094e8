"""Cost in accuracy of the stratified subsampling of the GP training set (issue #6), JSON lines.

    python benchmarks/gp_subsampling.py [FILE.h5 ...] [--campus] [--n 150 300 1000]
        [--set key=value ...] [--max-n N]

For every dataset and every n in `--n` (plus "all": the largest per-anchor range count, run only
when it is at most `--max-n`; a dense GP costs O(n^3) per likelihood step):

- `gp` with `n_train=n` (stratified by range, `gp.stratified_subsample`; `--set` adds GP
  parameters, e.g. `--set search=gradient`);
- `nls` as a control on a copy of the dataset whose ranges are the same kind of stratified
  subsample, n per anchor (so that the effect of fewer ranges is separated from that of the GP).

Printed per run: dataset, method, n_train, mean / median 3-D anchor error [m], seconds (one cold
call, JIT compilation included: every n is a new shape) and the 1-minute load average.
On a shared CPU set XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1".
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import numpy as np

from jaxcal.data import TrajectoryDataset
from jaxcal.errors import JaxcalError
from jaxcal.io import hdf5
from jaxcal.methods import calibrate
from jaxcal.trajectory.gp import stratified_subsample


def subsample_dataset(ds: TrajectoryDataset, n: int, seed: int = 0) -> TrajectoryDataset:
    """Copy of `ds` with at most `n` ranges per anchor (stratified by range, all tags together)."""
    keep = []
    for a in range(len(ds.anchor_ids)):
        idx = np.nonzero(np.asarray(ds.range_anchor) == a)[0]
        if idx.size:
            keep.append(idx[stratified_subsample(np.asarray(ds.range)[idx], n, 10, seed + a)])
    keep = np.sort(np.concatenate(keep))
    fields = {k: getattr(ds, k) for k in ds.__dataclass_fields__}
    for k in (
        "range_time",
        "range_anchor",
        "range_tag",
        "range",
        "range_los",
        "fp_rssi",
        "rx_rssi",
    ):
        if fields[k] is not None:
            fields[k] = np.asarray(fields[k])[keep]
    return TrajectoryDataset(**fields)


def one(ds, label, method, n, params):
    t0 = time.perf_counter()
    res = calibrate(ds, method, params)
    dt = time.perf_counter() - t0
    err = np.linalg.norm(res.position - ds.anchor_truth, axis=1)
    ok = np.isfinite(err)
    print(
        json.dumps(
            {
                "dataset": label,
                "method": method,
                "params": params,
                "n_train": n,
                "mean_error_m": round(float(err[ok].mean()), 4) if ok.any() else None,
                "median_error_m": round(float(np.median(err[ok])), 4) if ok.any() else None,
                "estimated": int(ok.sum()),
                "anchors": int(err.size),
                "seconds": round(dt, 2),
                "load1": round(os.getloadavg()[0], 2),
                "device": jax.devices()[0].platform,
            }
        ),
        flush=True,
    )


def parse_set(items):
    out = {}
    for it in items:
        k, _, v = it.partition("=")
        out[k] = v
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("files", nargs="*")
    ap.add_argument("--campus", action="store_true", help="also the simulated campus (no drift)")
    ap.add_argument("--n", type=int, nargs="+", default=[150, 300, 1000])
    ap.add_argument("--max-n", type=int, default=2500, help="run 'all' only up to this many")
    ap.add_argument("--set", action="append", default=[], help="extra GP parameter key=value")
    ap.add_argument("--skip-nls", action="store_true")
    a = ap.parse_args()
    datasets = [(hdf5.read(f), None) for f in a.files]
    if a.campus:
        from jaxcal.sim.trajectory import simulate

        datasets.append((simulate("campus", seed=0, drift=0.0), None))
    extra = parse_set(a.set)
    for ds, _ in datasets:
        counts = np.bincount(np.asarray(ds.range_anchor), minlength=len(ds.anchor_ids))
        n_all = int(counts.max())
        ns = sorted({n for n in a.n if n < n_all} | ({n_all} if n_all <= a.max_n else set()))
        for n in ns:
            one(ds, ds.name, "gp", n, dict(extra, n_train=n))
            if not a.skip_nls:
                one(subsample_dataset(ds, n), ds.name, "nls", n, {})
        if not a.skip_nls:
            one(ds, ds.name, "nls", n_all, {})


if __name__ == "__main__":
    try:
        main()
    except (JaxcalError, ValueError) as e:  # a missing or bad file, a bad --set: one line
        raise SystemExit(f"gp_subsampling: error: {e}") from None
