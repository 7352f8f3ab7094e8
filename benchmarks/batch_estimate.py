"""`--method batch`: posterior mean (`estimate=mean`, default) against the robust fit (`estimate=map`), in
expectation over resampled range errors on the real geometries.

One recording is one draw of the range errors; on a weak geometry two estimators can swap places from one
draw to the next. This script keeps each dwm1001-autocal scenario's true layout and redraws its errors
by a *pair permutation*: the error series of a pair (range - true distance, every epoch, both
directions) is moved as a whole to another pair (randomly ordered, directions randomly swapped). That
keeps what real DWM1001 errors have (per-pair systematic offsets, multipath, the network offset, missing
epochs) and only reassigns them. Each draw is solved with both estimates and with the SciPy soft_l1 peer
of `benchmarks/peers.py`; printed: aligned RMSE per draw, mean over the draws, and how often the mean
estimate beats the fit.

Usage:
    python benchmarks/batch_estimate.py [--draws 12] [--seed 0] [--scenarios 3D_distribution,...]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))

from peers import aligned_rmse, import_real, peer_scipy, peer_sklearn, truth_dim  # noqa: E402


def permuted_errors(range_m: np.ndarray, truth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The ranges of `truth`'s layout with the pairs' error series permuted (see the module docstring)."""
    r = np.asarray(range_m, dtype=np.float64)
    n = r.shape[1]
    d = np.linalg.norm(truth[:, None] - truth[None], axis=-1)
    err = r - d[None]
    iu, ju = np.triu_indices(n, 1)
    perm = rng.permutation(iu.size)
    swap = rng.random(iu.size) < 0.5
    out = np.full_like(r, np.nan)
    src_i = np.where(swap, ju[perm], iu[perm])
    src_j = np.where(swap, iu[perm], ju[perm])
    out[:, iu, ju] = d[iu, ju] + err[:, src_i, src_j]
    out[:, ju, iu] = d[iu, ju] + err[:, src_j, src_i]
    return out


def main(argv=None) -> int:
    from jaxcal.errors import JaxcalError
    from jaxcal.mesh.batch import BatchParams, solve

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scenarios", default="", help="comma-separated subset (default: all found)")
    args = ap.parse_args(argv)
    if args.draws < 1:
        print("batch_estimate: --draws must be >= 1", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        datasets = import_real(Path(tmp))
    if not datasets:
        print("batch_estimate: no dwm1001-autocal scenario found (../shared/datasets)", file=sys.stderr)
        return 1
    wanted = [s for s in args.scenarios.split(",") if s]
    datasets = [(n, ds) for n, ds in datasets if not wanted or any(w in n for w in wanted)]
    if not datasets:
        print(f"batch_estimate: no scenario matches --scenarios {args.scenarios}", file=sys.stderr)
        return 1
    summary = {}
    for name, ds in datasets:
        truth = np.asarray(ds.truth, dtype=np.float64)
        dim = truth_dim(ds)
        truth = truth[:, :dim]
        rng = np.random.default_rng(args.seed)
        rows = {"map": [], "mean": [], "scipy-soft_l1": []}
        for k in range(args.draws):
            r = permuted_errors(ds.range, truth, rng)
            t0 = time.perf_counter()
            for est in ("map", "mean"):
                try:
                    sol = solve(r, ds.config(None), BatchParams(dim=dim, estimate=est))
                    rows[est].append(aligned_rmse(sol.position, truth))
                except JaxcalError as e:  # a draw the solver refuses is counted as NaN, not a crash
                    print(f"# {name} draw {k} {est}: {e}", file=sys.stderr)
                    rows[est].append(float("nan"))
            rows["scipy-soft_l1"].append(aligned_rmse(peer_scipy(r, dim, peer_sklearn(r, dim)), truth))
            print(
                json.dumps(
                    {
                        "dataset": name,
                        "draw": k,
                        **{m: round(v[-1], 4) for m, v in rows.items()},
                        "seconds": round(time.perf_counter() - t0, 1),
                    }
                ),
                flush=True,
            )
        a, b = np.asarray(rows["mean"]), np.asarray(rows["map"])
        summary[name] = ({m: float(np.nanmean(v)) for m, v in rows.items()}, int(np.sum(a < b)))
    print(f"\nmean aligned RMSE [m] over {args.draws} pair-permutation draws (seed {args.seed})")
    print(f"{'dataset':28s} {'batch map':>10s} {'batch mean':>11s} {'scipy soft_l1':>14s}  mean<map")
    for name, (m, wins) in summary.items():
        print(f"{name:28s} {m['map']:10.3f} {m['mean']:11.3f} {m['scipy-soft_l1']:14.3f}  {wins}/{args.draws}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
