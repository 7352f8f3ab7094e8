"""Issue #19: ls, nls, gp (and a SciPy robust NLS) on real recordings and simulated families.

    python benchmarks/gp_families.py [FILE.h5 ...] [--seeds N] [--scenario campus|small ...]
        [--drift 0 0.05] [--offset 0 rand] [--nls KEY=VALUE ...] [--gp KEY=VALUE ...]
        [--methods ls nls gp scipy] > LOG
    python benchmarks/gp_families.py --table LOG ...      # the markdown table of the docs

Per dataset and method, one JSON line: mean 3-D anchor error over the anchors with an estimate
(a NaN height counts as horizontal error only), NEES/dof (e^T C^-1 e / dof over the estimated
axes, median over anchors), number of NaN-height anchors, seconds (one cold call: JIT compilation
included) and the 1-minute load average; the clock offset estimated and its sd where a method
estimated one. Simulated families: seeds 0..N-1 of each scenario, drift and pose clock offset
(`--offset rand`: uniform in +-0.3 s, drawn per seed; the campus has building blocks: links crossing
one are NLOS, a bias that persists along stretches of the route; drift is a horizontal random walk
of the reported poses).

`scipy`: what a user would write without jaxcal: per anchor `scipy.optimize.least_squares`
(`loss="soft_l1"`, `f_scale=0.3` m) on r_i = |p_i - a| + b over all ranges, started at the `ls`
answer, tag positions from the same pose interpolation (`prepare_poses`).
On a shared CPU set XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1".
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from jaxcal.io import hdf5
from jaxcal.methods import calibrate


def scipy_nls(ds):
    """Per-anchor SciPy robust least squares (see module doc); returns (A, 3) positions."""
    from scipy.optimize import least_squares

    from jaxcal.trajectory.common import multilaterate_all
    from jaxcal.trajectory.ls import LSParams
    from jaxcal.trajectory.poses import prepare_poses

    groups, _ = prepare_poses(ds, LSParams())
    pos, rng, mask = (np.asarray(a) for a in (groups.position, groups.range, groups.mask))
    init = np.asarray(multilaterate_all(groups.position, groups.range, groups.mask)[0])
    out = np.full((pos.shape[0], 3), np.nan)
    for a in range(pos.shape[0]):
        p, r = pos[a, mask[a]], rng[a, mask[a]]
        if r.size < 10 or not np.isfinite(init[a]).all():
            continue

        def res(x, p=p, r=r):
            return np.linalg.norm(p - x[:3], axis=1) + x[3] - r

        sol = least_squares(res, np.r_[init[a], 0.0], loss="soft_l1", f_scale=0.3)
        out[a] = sol.x[:3]
    return out


def evaluate(ds, method, params, label, true_offset=None):
    t0 = time.perf_counter()
    if method == "scipy":
        est, cov = scipy_nls(ds), None
    else:
        res = calibrate(ds, method, dict(params))
        est, cov = res.position, res.covariance
    sec = time.perf_counter() - t0
    truth = np.asarray(ds.anchor_truth)
    e = est - truth
    full = np.isfinite(e).all(axis=1)
    hor = np.isfinite(e[:, :2]).all(axis=1)
    err = np.where(full, np.linalg.norm(e, axis=1), np.linalg.norm(np.nan_to_num(e[:, :2]), axis=1))
    nees = None
    if cov is not None and hor.any():
        v = []
        for a in np.flatnonzero(hor):
            k = np.flatnonzero(np.isfinite(e[a]))  # a NaN height: the horizontal block
            v.append(e[a, k] @ np.linalg.solve(cov[a][np.ix_(k, k)], e[a, k]) / k.size)
        nees = float(np.median(v))
    out = {
        "dataset": label,
        "true_offset_s": true_offset,
        "offset_s": None if method == "scipy" else res.params.get("info_time_offset_estimate_s"),
        "offset_sd_s": None if method == "scipy" else res.params.get("info_time_offset_sd_s"),
        "method": method if not params else f"{method} {params}",
        "mean_error_m": float(err[hor].mean()) if hor.any() else None,
        "max_error_m": float(err[hor].max()) if hor.any() else None,
        "horizontal_m": float(np.linalg.norm(e[hor, :2], axis=1).mean()) if hor.any() else None,
        "nees_dof": nees,
        "nan_height": int((hor & ~full).sum()),
        "anchors": int(len(err)),
        "ranges": int(np.asarray(ds.range).size),
        "seconds": round(sec, 2),
        "load1": round(os.getloadavg()[0], 2),
    }
    print(json.dumps(out), flush=True)
    return out


def parse_set(items):
    out = {}
    for it in items or []:
        k, v = it.split("=", 1)
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def table(paths):
    """Markdown rows from JSON-lines logs of this script: per dataset (a family: median and worst
    over its seeds) and method, mean error [m], NEES/dof and seconds."""
    import re
    from collections import defaultdict

    rows = defaultdict(list)
    for path in paths:
        for line in open(path):
            if line.startswith("{"):
                d = json.loads(line)
                rows[(re.sub(r" seed=\d+", "", d["dataset"]), d["method"])].append(d)
    print(
        "| dataset | method | runs | mean error [m] median | worst | horizontal [m] median | "
        "NEES/dof median | worst | NaN heights | seconds median |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")

    def f(v):
        v = [x for x in v if x is not None and np.isfinite(x)]
        return (f"{np.median(v):.3g}", f"{np.max(v):.3g}") if v else ("-", "-")

    for (ds, m), ds_rows in rows.items():
        err, nees = f([d["mean_error_m"] for d in ds_rows]), f([d["nees_dof"] for d in ds_rows])
        hor = f([d["horizontal_m"] for d in ds_rows])[0]
        nan_h = sum(d["nan_height"] for d in ds_rows)
        sec = np.median([d["seconds"] for d in ds_rows])
        print(
            f"| {ds} | {m} | {len(ds_rows)} | {err[0]} | {err[1]} | {hor} | {nees[0]} | "
            f"{nees[1]} | {nan_h} | {sec:.1f} |"
        )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--table", nargs="*", help="print the markdown table of these logs and exit")
    ap.add_argument("files", nargs="*")
    ap.add_argument("--seeds", type=int, default=0)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--seed-step", type=int, default=1, help="2: every other seed (a development or report half)")
    ap.add_argument("--scenario", nargs="*", default=["campus"])
    ap.add_argument("--drift", nargs="*", type=float, default=[0.0, 0.05])
    ap.add_argument("--methods", nargs="*", default=["ls", "nls", "gp", "scipy"])
    ap.add_argument(
        "--offset",
        nargs="*",
        default=["0"],
        help="pose clock offsets of the simulated families [s]: numbers, or 'rand' (uniform in +-0.3 s per seed)",
    )
    ap.add_argument("--nls", nargs="*", help="extra nls configs, each KEY=VALUE[,KEY=VALUE]")
    ap.add_argument("--gp", nargs="*", help="extra gp configs, each KEY=VALUE[,KEY=VALUE]")
    a = ap.parse_args()
    if a.table:
        table(a.table)
        return
    configs = [(m, {}) for m in a.methods]
    for g in a.nls or []:
        configs.append(("nls", parse_set(g.split(","))))
    for g in a.gp or []:
        configs.append(("gp", parse_set(g.split(","))))
    for f in a.files:
        ds = hdf5.read(f)
        for m, p in configs:
            evaluate(ds, m, p, os.path.basename(f))
    if a.seeds:
        from jaxcal.sim.trajectory import simulate

        for sc in a.scenario:
            for drift in a.drift:
                for seed in range(a.first_seed, a.first_seed + a.seeds * a.seed_step, a.seed_step):
                    for off in a.offset:
                        t = (
                            float(np.random.default_rng(1000 + seed).uniform(-0.3, 0.3))
                            if off == "rand"
                            else float(off)
                        )
                        ds = simulate(sc, seed=seed, drift=drift, time_offset_s=t)
                        name = f"{sc} drift={drift:g}" + (f" offset={off}" if off != "0" else "") + f" seed={seed}"
                        for m, p in configs:
                            evaluate(ds, m, p, name, t)


if __name__ == "__main__":
    main()
