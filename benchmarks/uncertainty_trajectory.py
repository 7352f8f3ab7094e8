"""Do the trajectory methods' anchor covariances hold the truth? NEES and coverage per anchor.

Datasets: the real recordings in ../shared/datasets with anchor truth (hymn-torgau, hanyang-outdoor LOS and
NLOS Trajectory_A Case_1, cuhksz-planar) and simulated campaigns (`jaxcal.sim.trajectory`, scenario
`small` (`--scenario campus`: the full-scale campus, 10 anchors over 600 x 450 m) over `--sim-seeds`;
`--family alternate` (default): odometry drift 0.02 m/sqrt(s) on odd seeds, none on
even ones; `drift` / `clean`: drift on every seed / on none). `--stated-drift` tells the methods the drift
(`pose_drift`, `jaxcal.trajectory.pose_error`) where there is one; otherwise nls estimates it from the ranges
(`jaxcal.trajectory.drift`, `--drift-estimate on|off`, for nls and gp alike; each line's `pose_drift_estimate`,
`pose_drift_used` and `pose_error_model`).

Per anchor with a finite estimate: the error e (3-D; split into horizontal and vertical), the NEES
e^T C^-1 e over the finite coordinates (an unobservable coordinate reported as NaN is left out, and
counted), and whether the truth is inside the 95 % ellipsoid; the same for the horizontal (x, y) and vertical
(z) parts apart. Printed (JSON lines): one line per (dataset, method), then one summary line per method
over the simulated campaigns (coverage as the mean of the campaigns' and, `coverage95_h` / `_v`, pooled over
all anchors; `outside95` = anchors reported as fixed whose truth is outside: confidently wrong; mean errors
over anchors, 3-D over the finite coordinates and horizontal).

Usage:
    python benchmarks/uncertainty_trajectory.py [--methods nls,ls] [--sim-seeds 0-19 | 1,3,5] [--no-real]
        [--scenario small|campus] [--family alternate|drift|clean] [--stated-drift] [--drift-estimate on|off]
        [--drift-model auto|drift|bounded]
        [--nls-set K=V ...]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np
from scipy.stats import chi2

SHARED = Path(__file__).resolve().parents[2] / "shared" / "datasets"


def real_datasets():
    from jaxcal.io.importers.cuhksz import import_cuhksz
    from jaxcal.io.importers.hanyang import import_hanyang
    from jaxcal.io.importers.hymn import import_hymn

    out = []
    if (SHARED / "hymn-torgau").exists():
        out.append(("hymn-torgau", lambda: import_hymn(SHARED / "hymn-torgau")))
    for cls in ("LOS", "NLOS"):
        d = SHARED / "hanyang-outdoor" / cls / "Trajectory_A" / "Case_1"
        if d.exists():
            out.append((f"hanyang-{cls}", lambda d=d: import_hanyang(d)))
    d = SHARED / "cuhksz-planar" / "Dynamic"
    if d.exists():
        out.append(
            (
                "cuhksz-planar",
                lambda d=d: import_cuhksz(d / "UWB_dynamic_exp_mid.csv", d / "motion_capture_dynamic_exp_mid.csv"),
            )
        )
    return out


def anchor_figures(res, truth) -> list[dict]:
    rows = []
    for k in range(truth.shape[0]):
        x, c, t = res.position[k], res.covariance[k], truth[k]
        fin = np.isfinite(x)
        if not fin.any() or not np.isfinite(t).all():
            continue
        e = x - t
        row = {
            "anchor": k,
            "error_m": float(np.linalg.norm(e[fin])),
            "h_error_m": float(np.linalg.norm(e[:2])),
            "v_error_m": float(abs(e[2])) if fin[2] else float("nan"),
            "nan_axes": int((~fin).sum()),
        }
        cf = c[np.ix_(fin, fin)]
        if np.isfinite(cf).all():
            q = float(e[fin] @ np.linalg.lstsq(cf, e[fin], rcond=None)[0])
            row.update(
                nees=q,
                dof=int(fin.sum()),
                inside=bool(q <= chi2.ppf(0.95, int(fin.sum()))),
                sd_m=float(np.sqrt(np.trace(cf))),
                h_nees=float(e[:2] @ np.linalg.solve(c[:2, :2], e[:2])),
            )
            row["h_inside"] = bool(row["h_nees"] <= chi2.ppf(0.95, 2))
            if fin[2]:
                row["v_nees"] = float(e[2] ** 2 / c[2, 2])
                row["v_inside"] = bool(row["v_nees"] <= chi2.ppf(0.95, 1))
        rows.append(row)
    return rows


def line(label, method, rows):
    used = [r for r in rows if "nees" in r]
    dof = sum(r["dof"] for r in used)
    return {
        "dataset": label,
        "method": method,
        "anchors": len(rows),
        "nees_per_dof": sum(r["nees"] for r in used) / dof if dof else float("nan"),
        "h_nees_per_dof": sum(r["h_nees"] for r in used) / (2 * len(used)) if used else float("nan"),
        "v_nees_per_dof": float(np.mean(v)) if (v := [r["v_nees"] for r in used if "v_nees" in r]) else float("nan"),
        "outside95": sum(not r["inside"] for r in used),
        "coverage95": float(np.mean([r["inside"] for r in used])) if used else float("nan"),
        "inside_h": [sum(r["h_inside"] for r in used), len(used)],
        "inside_v": [sum(r["v_inside"] for r in used if "v_inside" in r), sum("v_inside" in r for r in used)],
        "mean_error_m": float(np.mean([r["error_m"] for r in rows])) if rows else float("nan"),
        "mean_h_error_m": float(np.mean([r["h_error_m"] for r in rows])) if rows else float("nan"),
        "rmse_m": float(np.sqrt(np.mean([r["error_m"] ** 2 for r in used]))) if used else float("nan"),
        "pred_rmse_m": float(np.sqrt(np.mean([r["sd_m"] ** 2 for r in used]))) if used else float("nan"),
        "nan_axes": sum(r["nan_axes"] for r in rows),
        "worst": max(used, key=lambda r: r["nees"], default=None),
        # the anchors with a fixed height apart from those whose height is NaN (their horizontal ellipse holds
        # the fit at every height the ranges cannot tell apart: `jaxcal.trajectory.mirror`, step 5)
        "fixed_nees_per_dof": _per_dof([r for r in used if r["nan_axes"] == 0]),
        "nan_height_nees_per_dof": _per_dof([r for r in used if r["nan_axes"] > 0]),
    }


def _per_dof(rows) -> float:
    dof = sum(r["dof"] for r in rows)
    return sum(r["nees"] for r in rows) / dof if dof else float("nan")


def _nanmedian(values) -> float | None:
    v = [x for x in values if np.isfinite(x)]
    return float(np.median(v)) if v else None


def _pooled(lines, key):
    """Fraction inside over all campaigns' anchors, from each line's [inside, counted]."""
    inside, counted = (sum(x[key][i] for x in lines) for i in (0, 1))
    return inside / counted if counted else None


def _seed_range(text: str) -> range:
    a, _, b = text.partition("-")
    return range(int(a), int(b or a) + 1)


def main(argv=None) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", default="nls,ls")
    ap.add_argument("--sim-seeds", default="0-19")
    ap.add_argument("--no-real", action="store_true")
    ap.add_argument("--family", choices=("alternate", "drift", "clean"), default="alternate")
    ap.add_argument("--scenario", choices=("small", "campus"), default="small")
    ap.add_argument("--stated-drift", action="store_true", help="pass the campaign's drift as pose_drift")
    ap.add_argument("--drift-estimate", choices=("on", "off", "default"), default="default", help="nls, gp")
    ap.add_argument("--drift-model", choices=("auto", "drift", "bounded"), default=None, help="drift_model (nls, gp)")
    ap.add_argument("--nls-set", action="append", default=[], metavar="K=V", help="an NLSParams value for nls")
    args = ap.parse_args(argv)
    logging.getLogger("jaxcal").setLevel(logging.ERROR)
    from jaxcal.methods import calibrate
    from jaxcal.sim.trajectory import simulate

    methods = args.methods.split(",")
    off = {} if args.drift_estimate == "default" else {"estimate_drift": args.drift_estimate == "on"}
    if args.drift_model is not None:
        off["drift_model"] = args.drift_model
    nls_only = {}
    for kv in args.nls_set:
        k, v = kv.split("=", 1)
        nls_only[k] = json.loads(v) if v[:1] in "-0123456789.tf[" else v

    def run(ds, m, params):
        extra = {**off, **(nls_only if m == "nls" else {})}
        res = calibrate(ds, m, params={**extra, **(params or {})} if m in ("nls", "gp") else params)
        ln = line(ds.name, m, anchor_figures(res, ds.anchor_truth))
        ln["pose_drift_used"] = res.params.get("pose_drift")
        ln["pose_drift_estimate"] = res.params.get("info_pose_drift_estimate")
        ln["pose_error_model"] = res.params.get("info_pose_error_model")
        return ln

    if not args.no_real:
        for label, load in real_datasets():
            ds = load()
            for m in methods:
                print(json.dumps(dict(run(ds, m, None), dataset=label)), flush=True)
    seeds = [s for part in filter(None, args.sim_seeds.split(",")) for s in _seed_range(part)]  # "": none
    sims = {m: [] for m in methods}
    for seed in seeds:
        drift = {"drift": 0.02, "clean": 0.0}.get(args.family, 0.02 if seed % 2 else 0.0)
        ds = simulate(args.scenario, seed=seed, drift=drift)
        stated = {"pose_drift": drift} if args.stated_drift and drift > 0 else None
        for m in methods:
            ln = dict(run(ds, m, stated), dataset=f"sim-{args.scenario}-{seed}")
            sims[m].append(ln)
            print(json.dumps(ln), flush=True)
    for m in methods:
        nees = [x["nees_per_dof"] for x in sims[m] if np.isfinite(x["nees_per_dof"])]
        cov = [x["coverage95"] for x in sims[m] if np.isfinite(x["coverage95"])]
        print(
            json.dumps(
                {
                    "summary": m,
                    "campaigns": len(sims[m]),
                    "coverage95_mean": float(np.mean(cov)) if cov else None,
                    "nees_dof_median": float(np.median(nees)) if nees else None,
                    "nees_dof_worst": float(np.max(nees)) if nees else None,
                    "outside95": sum(x["outside95"] for x in sims[m]),
                    "nan_heights": sum(x["nan_axes"] for x in sims[m]),
                    "fixed_nees_dof_median": _nanmedian([x["fixed_nees_per_dof"] for x in sims[m]]),
                    "nan_height_nees_dof_median": _nanmedian([x["nan_height_nees_per_dof"] for x in sims[m]]),
                    "coverage95_h": _pooled(sims[m], "inside_h"),
                    "coverage95_v": _pooled(sims[m], "inside_v"),
                    "mean_error_m": float(np.mean([x["mean_error_m"] for x in sims[m]])) if sims[m] else None,
                    "mean_h_error_m": float(np.mean([x["mean_h_error_m"] for x in sims[m]])) if sims[m] else None,
                }
            ),
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
