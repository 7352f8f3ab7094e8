"""Availability and RMSE of the mesh methods on the frame families (issue #18, #24 item 1).

For every family of `jaxcal.sim.families` (frame pair a0-a1 / a0-a2 / a1-a2 never measured, a node joining
at half time, two clusters joined by one node, a node with one neighbour) and every seed, each method
calibrates in the frame (0, 1, 2); `jaxcal.mesh.identify` says which nodes the ranges fix. Per run:

- `placed`: share of the fixed nodes with a final estimate; `extra`: nodes placed that the ranges do
  not fix (must be 0);
- `avail`: the least, over fixed nodes other than a0, availability after the node's first range (share of
  the epochs from its first range on with an estimate; methods without a track: 1 when placed);
- `rmse`: RMS of the final errors over placed nodes other than a0 [m] in the frame (truth moved into it).

Prints one JSON line per run, then a Markdown table (median and worst over seeds per family and method).

    PYTHONPATH=src python benchmarks/frame_families.py --seeds 20 --epochs 400
    PYTHONPATH=src python benchmarks/frame_families.py --torgau   # before/after on data/torgau.h5
    python benchmarks/frame_families.py --table run1.log run2.log    # one table from several runs' lines
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

# fixed grid for pgp / parametric (the cap binds for every layout: one compilation per method)
PGP = {"extent_m": 38.0, "margin_m": 40.0}
BATCH = {"estimate": "map"}  # the mask is the point here; the covariance is issue #24's


def run_one(ds, method: str, frame_mode: str = "auto"):
    from jaxcal.mesh.identify import identify_ranges
    from jaxcal.methods import calibrate

    params = dict(PGP) if method in ("pgp", "parametric") else dict(BATCH) if method == "batch" else {}
    if method in ("pgp", "parametric"):
        params["frame"] = frame_mode
    t0 = time.perf_counter()
    res = calibrate(ds, method, params)
    secs = time.perf_counter() - t0
    return res, secs, identify_ranges(ds.range, (0, 1, 2), ids=ds.node_ids)


def score(ds, res, ident) -> dict:
    from jaxcal.metrics import truth_in_result_frame

    truth = truth_in_result_frame(res, ds.truth)
    n = ds.n_nodes
    placed = np.isfinite(res.position).all(axis=1)
    fixed = ident.fixed
    others = np.arange(n) != 0
    err = np.linalg.norm(res.position - truth, axis=1)
    sel = placed & others
    rmse = float(np.sqrt(np.mean(err[sel] ** 2))) if sel.any() else float("nan")
    fin = np.isfinite(ds.range)
    seen = fin.any(axis=2) | fin.any(axis=1)  # (K, N): node ranged this epoch
    avail = []
    for i in np.flatnonzero(fixed & others):
        first = np.flatnonzero(seen[:, i])
        if res.track_position is None:
            avail.append(1.0 if placed[i] else 0.0)
        elif first.size:
            has = np.isfinite(res.track_position[first[0] :, i]).all(axis=1)
            avail.append(float(has.mean()))
    return {
        "fixed": int(fixed.sum()),
        "placed": float((placed & fixed).sum() / max(fixed.sum(), 1)),
        "extra": int((placed & ~fixed).sum()),
        "avail": float(min(avail)) if avail else float("nan"),
        "rmse": rmse,
    }


def families(args) -> list[dict]:
    from jaxcal.sim.families import FAMILIES, family_mesh

    rows = []
    fams = args.families.split(",") if args.families else FAMILIES
    for kind in fams:
        for seed in range(args.seeds):
            ds = family_mesh(kind, seed, n_nodes=args.nodes, n_epochs=args.epochs)
            for method in args.methods.split(","):
                mode = "auto"
                if method == "pgp-direct" and kind not in ("a0a1", "a0a2", "a1a2"):
                    continue  # the same run as pgp: its own frame is measured
                if method == "pgp-direct":
                    method, mode = "pgp", "direct"
                res, secs, ident = run_one(ds, method, mode)
                row = {
                    "family": kind,
                    "seed": seed,
                    "method": method + ("-direct" if mode == "direct" else ""),
                    "seconds": round(secs, 2),
                    **score(ds, res, ident),
                }
                print(json.dumps(row), flush=True)
                rows.append(row)
    return rows


def table(rows: list[dict]) -> str:
    out = [
        "| family | method | runs | fixed nodes (median) | placed share: median / worst | "
        "extra placed (total) | availability: median / worst | RMSE [m]: median / worst |",
        "|---|---|---|---|---|---|---|---|",
    ]
    keys = sorted({(r["family"], r["method"]) for r in rows}, key=lambda k: (k[0], k[1]))
    for fam, meth in keys:
        rs = [r for r in rows if r["family"] == fam and r["method"] == meth]
        pl = np.array([r["placed"] for r in rs])
        av = np.array([r["avail"] for r in rs], dtype=float)
        rm = np.array([r["rmse"] for r in rs], dtype=float)

        def worst(x):
            return float(np.max(np.where(np.isfinite(x), x, np.inf))) if x.size else float("nan")

        def med(x):
            return float(np.median(x[np.isfinite(x)])) if np.isfinite(x).any() else float("nan")

        out.append(
            f"| {fam} | {meth} | {len(rs)} | {np.median([r['fixed'] for r in rs]):.0f} | "
            f"{np.median(pl):.2f} / {pl.min():.2f} | {sum(r['extra'] for r in rs)} | "
            f"{med(av):.3f} / {np.nanmin(av) if np.isfinite(av).any() else float('nan'):.3f} | "
            f"{med(rm):.2f} / {worst(rm):.2f} |"
        )
    return "\n".join(out)


def torgau(args) -> None:
    """Before (the tree at --before, e.g. /work/main/src) and after (this tree) on data/torgau.h5 with
    conf1's a0-a1 pair removed, through the CLI."""
    from jaxcal.io import hdf5

    ds = hdf5.read(ROOT / "data" / "torgau.h5")
    a0, a1, _ = ds.config("conf1")
    r = np.array(ds.range)
    r[:, a0, a1] = r[:, a1, a0] = np.nan
    import dataclasses

    cut = dataclasses.replace(ds, range=r, name="torgau-no-a0a1")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "torgau_cut.h5"
        hdf5.write(path, cut)
        for label, src in (("before", args.before), ("after", str(ROOT / "src"))):
            for method in args.methods.split(","):
                if method == "pgp-direct":
                    continue
                out = Path(tmp) / f"{label}_{method}.h5"
                env = {**os.environ, "PYTHONPATH": src, "JAX_PLATFORMS": os.environ.get("JAX_PLATFORMS", "cpu")}
                extra = ["--set", "estimate=map"] if method == "batch" else []
                t0 = time.perf_counter()
                p = subprocess.run(
                    [
                        sys.executable,
                        "-m",
                        "jaxcal.cli",
                        "calibrate",
                        str(path),
                        "--method",
                        method,
                        "--config",
                        "conf1",
                        "-o",
                        str(out),
                        *extra,
                    ],
                    capture_output=True,
                    text=True,
                    env=env,
                )
                secs = time.perf_counter() - t0
                row = {
                    "torgau": label,
                    "method": method,
                    "rc": p.returncode,
                    "seconds": round(secs, 1),
                    "stdout": p.stdout.strip()[-300:],
                    "stderr": p.stderr.strip()[-400:],
                }
                if p.returncode == 0:
                    e = subprocess.run(
                        [sys.executable, "-m", "jaxcal.cli", "evaluate", str(out), "--truth", str(path), "--json"],
                        capture_output=True,
                        text=True,
                        env=env,
                    )
                    if e.returncode == 0:
                        rep = json.loads(e.stdout)
                        av = [nd["availability"] for nd in rep["nodes"]]
                        placed = sum(1 for nd in rep["nodes"] if nd["final_error_m"] is not None)
                        row.update(
                            rmse_m=rep["rmse_m"],
                            final_rmse_m=rep["final_rmse_m"],
                            placed=placed,
                            min_availability=min(av),
                            nodes=len(av),
                        )
                print(json.dumps(row), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--epochs", type=int, default=400)
    ap.add_argument("--nodes", type=int, default=12)
    ap.add_argument("--families", default="")
    ap.add_argument("--methods", default="cf,pgp,parametric,batch,pgp-direct")
    ap.add_argument("--torgau", action="store_true", help="before/after on data/torgau.h5 instead")
    ap.add_argument("--before", default="/work/main/src", help="source tree of the 'before' run")
    ap.add_argument("--table", nargs="+", metavar="LOG", help="only print the table of these JSON-lines logs")
    args = ap.parse_args()
    if args.table:
        rows = []
        for path in args.table:
            for line in Path(path).read_text().splitlines():
                if line.startswith("{") and '"family"' in line:
                    rows.append(json.loads(line))
        print(table(rows))
        return
    logging.getLogger("jaxcal").setLevel(logging.ERROR)
    import jax

    print(json.dumps({"device": str(jax.devices()[0]), "load": os.getloadavg()}), flush=True)
    if args.torgau:
        torgau(args)
        return
    rows = families(args)
    print(table(rows))


if __name__ == "__main__":
    main()
