"""jaxcal's mesh methods next to the tools a user would otherwise reach for, on the same files.

Peers (written as a user would write them, not tuned):
- `sklearn-smacof`: `sklearn.manifold.MDS` (metric SMACOF, precomputed dissimilarities) on the per-pair
  median distance matrix; pairs never measured are filled with shortest-path lengths over the measured
  links (scikit-learn's MDS does not accept missing entries).
- `scipy-soft_l1`: `scipy.optimize.least_squares(loss="soft_l1", f_scale=0.2)` on the measured per-pair
  medians, started from the scikit-learn SMACOF solution.

Datasets: simulated `torgau` (jaxcal.sim.mesh) and the three dwm1001-autocal scenarios, each in the
frame configurations of `--configs` that the file has (conf1 and conf2 by default), imported at run time
with `jaxcal import dwm1001-autocal` from
../shared/datasets into a temporary folder (those files must not be copied into the project).

Metric: aligned RMSE [m] of the final positions after the best rigid motion (with reflection) onto the
truth (2-D estimates against the first two truth axes; 3-D when the truth is 3-D and not planar).

Usage:
    python benchmarks/peers.py [--methods batch,pgp,...] [--seeds 0] [--skip-real] [--skip-sim]
Prints one JSON object per (dataset, method) and a table at the end.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "datasets" / "dwm1001-autocal"
DWM_SCENARIOS = {  # name -> (scenario folder, nodes_cfg stem)
    "dwm1001-campus_sport": ("campus_sport/rich_samples", "campus_sport"),
    "dwm1001-srvlab_ground": ("srvlab_ground", "srvlab_ground"),
    "dwm1001-3D_distribution": ("3D_distribution", "3D_distribution"),
}
PEERS = ("sklearn-smacof", "scipy-soft_l1")


def median_matrix(range_m: np.ndarray) -> np.ndarray:
    """(N, N) symmetric per-pair median range [m] (both directions pooled); NaN = never measured."""
    r = np.concatenate([range_m, np.swapaxes(range_m, 1, 2)], axis=0).astype(np.float64)
    n = r.shape[1]
    med = np.full((n, n), np.nan)
    ii, jj = np.nonzero(np.isfinite(r).any(axis=0))
    med[ii, jj] = np.nanmedian(r[:, ii, jj], axis=0)
    np.fill_diagonal(med, 0.0)
    return med


def peer_sklearn(range_m: np.ndarray, dim: int, seed: int = 0) -> np.ndarray:
    """scikit-learn metric SMACOF on the shortest-path-completed median matrix."""
    from scipy.sparse.csgraph import shortest_path
    from sklearn.manifold import MDS

    med = median_matrix(range_m)
    graph = np.where(np.isfinite(med), med, 0.0)  # 0 = no edge for csgraph
    full = np.where(np.isfinite(med), med, shortest_path(graph, directed=False))
    full = np.where(np.isfinite(full), full, np.nanmax(full[np.isfinite(full)]))
    try:  # scikit-learn >= 1.8 spells it metric_mds / metric="precomputed"
        mds = MDS(n_components=dim, metric_mds=True, metric="precomputed", n_init=4, init="random", random_state=seed)
    except TypeError:
        mds = MDS(n_components=dim, metric=True, dissimilarity="precomputed", n_init=4, random_state=seed)
    return mds.fit_transform(full)


def peer_scipy(range_m: np.ndarray, dim: int, x0: np.ndarray) -> np.ndarray:
    """SciPy robust least squares (soft_l1) on the measured median pairs, from an MDS start."""
    from scipy.optimize import least_squares

    med = median_matrix(range_m)
    iu, ju = np.triu_indices(med.shape[0], k=1)
    ok = np.isfinite(med[iu, ju])
    i, j, z = iu[ok], ju[ok], med[iu, ju][ok]

    def fun(theta):
        x = theta.reshape(-1, dim)
        return np.linalg.norm(x[i] - x[j], axis=1) - z

    sol = least_squares(fun, x0.ravel(), loss="soft_l1", f_scale=0.2)
    return sol.x.reshape(-1, dim)


def aligned_rmse(est: np.ndarray, truth: np.ndarray) -> float:
    """RMSE [m] after the best rigid motion with reflection (rows finite in both)."""
    from jaxcal.mesh.frame import align_rigid, apply_rigid

    d = est.shape[1]
    t = truth[:, :d] if truth.shape[1] >= d else np.pad(truth, ((0, 0), (0, d - truth.shape[1])))
    ok = np.isfinite(est).all(axis=1) & np.isfinite(t).all(axis=1)
    if ok.sum() < 3:
        return float("nan")
    r, tr = align_rigid(est[ok], t[ok], reflection=True)
    e = np.linalg.norm(apply_rigid(est[ok], r, tr) - t[ok], axis=1)
    return float(np.sqrt(np.mean(e * e)))


def import_dwm(tmp: Path, name: str, folder: str, cfg: str):
    """One dwm1001-autocal scenario via `jaxcal import dwm1001-autocal` into `tmp`; None (said) when it fails."""
    from jaxcal.io import hdf5

    dst = tmp / f"{name}.h5"
    cmd = [sys.executable, "-m", "jaxcal.cli", "import", "dwm1001-autocal", str(SHARED / folder)]
    cmd += [str(SHARED / "nodes_cfg" / f"{cfg}.yaml"), "-o", str(dst), "--name", name]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        print(f"# import {name} failed: {proc.stderr.strip()}", file=sys.stderr)
        return None
    return hdf5.read(dst)


def import_real(tmp: Path) -> list[tuple[str, object]]:
    """The dwm1001-autocal scenarios, via `jaxcal import dwm1001-autocal` (skipped when absent)."""
    if not SHARED.exists():
        print(f"# {SHARED} not found: real scenarios skipped", file=sys.stderr)
        return []
    out = []
    for name, (folder, cfg) in DWM_SCENARIOS.items():
        data = import_dwm(tmp, name, folder, cfg)
        if data is not None:
            out.append((name, data))
    return out


def truth_dim(ds) -> int:
    t = ds.truth
    return 3 if t.shape[1] == 3 and np.nanmax(t[:, 2]) - np.nanmin(t[:, 2]) > 0.5 else 2


def main(argv=None) -> int:
    from jaxcal.methods import MESH_METHODS, calibrate
    from jaxcal.sim.mesh import simulate

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", default=",".join(MESH_METHODS), help="jaxcal mesh methods to run")
    ap.add_argument("--seeds", default="0", help="simulation seeds, comma separated")
    ap.add_argument("--configs", default="conf1,conf2", help="frame configurations to run (each file's that exist)")
    ap.add_argument("--skip-real", action="store_true")
    ap.add_argument("--skip-sim", action="store_true")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="METHOD:KEY=VALUE",
        help="parameter override for one jaxcal method (e.g. batch:loss=huber)",
    )
    args = ap.parse_args(argv)
    methods = [m for m in args.methods.split(",") if m]
    overrides: dict[str, dict[str, str]] = {}
    for item in args.set:
        meth, _, kv = item.partition(":")
        k, _, v = kv.partition("=")
        overrides.setdefault(meth, {})[k] = v

    runs = []  # (dataset label, dataset, config)
    with tempfile.TemporaryDirectory() as tmpdir:
        if not args.skip_sim:
            for seed in (int(s) for s in args.seeds.split(",")):
                ds = simulate("torgau", seed=seed)
                for conf in args.configs.split(","):
                    runs.append((f"torgau-s{seed}/{conf}", ds, conf))
        if not args.skip_real:
            for name, ds in import_real(Path(tmpdir)):
                confs = [c for c in args.configs.split(",") if c in dict(ds.configs)] or [None]
                for conf in confs:
                    runs.append((f"{name}/{conf or 'default'}", ds, conf))

        table: dict[str, dict[str, float]] = {}
        for label, ds, conf in runs:
            dim = truth_dim(ds)
            row = table.setdefault(label, {})
            rec_base = {
                "dataset": label,
                "nodes": ds.n_nodes,
                "epochs": ds.n_epochs,
                "dim": dim,
                "device": jax.devices()[0].platform,
                "host": platform.node(),
            }
            for meth in methods:
                params = dict(overrides.get(meth, {}))
                if dim == 3 and meth.endswith("batch") and "dim" not in params:
                    params["dim"] = "3"
                t0 = time.perf_counter()
                try:
                    res = calibrate(ds, meth, params=params, config=conf)
                    rmse = aligned_rmse(res.position, ds.truth)
                    err = None
                except Exception as e:  # a method failing on a file is a result, not a crash
                    rmse, err = float("nan"), f"{type(e).__name__}: {e}".splitlines()[0]
                    if "--debug" in sys.argv:
                        traceback.print_exc()
                row[meth] = rmse
                print(
                    json.dumps(
                        {
                            **rec_base,
                            "method": meth,
                            "kind": "jaxcal",
                            "params": params,
                            "aligned_rmse_m": rmse,
                            "seconds": time.perf_counter() - t0,
                            "error": err,
                        }
                    ),
                    flush=True,
                )
            t0 = time.perf_counter()
            x_sk = peer_sklearn(ds.range, dim)
            t_sk = time.perf_counter() - t0
            x_sp = peer_scipy(ds.range, dim, x_sk)
            t_sp = time.perf_counter() - t0
            for meth, x, sec in (("sklearn-smacof", x_sk, t_sk), ("scipy-soft_l1", x_sp, t_sp)):
                row[meth] = aligned_rmse(x, ds.truth)
                print(
                    json.dumps(
                        {
                            **rec_base,
                            "method": meth,
                            "kind": "peer",
                            "aligned_rmse_m": row[meth],
                            "seconds": sec,
                            "error": None,
                        }
                    ),
                    flush=True,
                )

    cols = methods + list(PEERS)
    w = max([len(k) for k in table] + [8])
    hybrid = "pgp" in methods and "pgp+batch" in methods
    print("\naligned RMSE [m]")
    print(
        f"{'dataset':{w}s} "
        + " ".join(f"{c:>14s}" for c in cols)
        + "  best-jaxcal  beats-peers"
        + ("  pgp+batch<=pgp" if hybrid else "")
    )
    for label, row in table.items():
        best_j = min((row[m] for m in methods if np.isfinite(row[m])), default=float("nan"))
        best_p = min(row[p] for p in PEERS)
        cells = " ".join(f"{row[c]:14.3f}" for c in cols)
        line = f"{label:{w}s} {cells}  {best_j:11.3f}  {'yes' if best_j < best_p else 'NO':>11s}"
        if hybrid:  # a pgp that failed (NaN) cannot be beaten or lost to
            ok = not np.isfinite(row["pgp"]) or row["pgp+batch"] <= row["pgp"]
            line += f"  {'yes' if ok else 'NO':>14s}"
        print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
