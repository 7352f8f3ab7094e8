"""Straight roads, where the path's symmetry hides part of each anchor's position (`jaxcal.trajectory.path_shape`):
one anchor per campaign beside a straight 120 m road (`tests/trajectory_campaigns.py::straight_road`), per road
kind and seed. One JSON line per campaign (coordinates kept, error over them, largest sd, NEES per kept dof), then
one summary line per road kind (docs/benchmarks/uncertainty.md, twenty-second round).

    PYTHONPATH=src python benchmarks/straight_roads.py [--method nls] [--roads flat,hills,weave0.5,weave0.03,diagonal]
        [--seeds 0-19]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from trajectory_campaigns import straight_road  # noqa: E402

ROADS = {
    "flat": {},
    "hills": {"hill": 1.5},
    "weave0.5": {"hill": 1.5, "wiggle": 0.5},
    "weave0.03": {"hill": 1.5, "wiggle": 0.03},
    "diagonal": {"heading": np.pi / 4},
}
CHI2_95 = {1: 3.841458820694124, 2: 5.991464547107979, 3: 7.814727903251178}


def one(method, road: str, seed: int) -> dict:
    ds, _ = straight_road(seed, **ROADS[road])
    res = method.calibrate(ds, {})
    e = res.position[0] - ds.anchor_truth[0]
    ok = np.isfinite(e)
    row = {"road": road, "seed": seed, "kept": "".join(c for c, k in zip("xyz", ok, strict=True) if k)}
    if ok.any():
        c = res.covariance[0][np.ix_(ok, ok)]
        nees = float(e[ok] @ np.linalg.solve(c, e[ok]))
        row.update(
            error_m=float(np.linalg.norm(e[ok])),
            max_sd_m=float(np.sqrt(np.linalg.eigvalsh(c).max())),
            nees_per_dof=nees / ok.sum(),
            outside95=nees > CHI2_95[int(ok.sum())],
        )
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--method", default="nls", choices=("nls", "gp", "ls"))
    ap.add_argument("--roads", default=",".join(ROADS))
    ap.add_argument("--seeds", default="0-19", help="first-last (default 0-19)")
    a = ap.parse_args()
    logging.getLogger("jaxcal").setLevel(logging.ERROR)
    from jaxcal.trajectory import gp, ls, nls

    method = {"nls": nls, "gp": gp, "ls": ls}[a.method]
    lo, _, hi = a.seeds.partition("-")
    try:
        seeds = range(int(lo), int(hi or lo) + 1)
    except ValueError:
        raise SystemExit(f"straight_roads.py: --seeds: expected FIRST-LAST (e.g. 0-19), got {a.seeds!r}") from None
    roads = a.roads.split(",")
    for road in roads:  # checked before any fit runs
        if road not in ROADS:
            raise SystemExit(f"straight_roads.py: --roads: {road!r} is not one of {', '.join(ROADS)}")
    for road in roads:
        rows = [one(method, road, s) for s in seeds]
        for r in rows:
            print(json.dumps(r), flush=True)
        kept = [r for r in rows if r["kept"]]
        figs = {k: [r[k] for r in kept] for k in ("error_m", "nees_per_dof")}
        print(
            json.dumps(
                {
                    "summary": road,
                    "method": a.method,
                    "campaigns": len(rows),
                    "kept": dict(Counter(r["kept"] for r in rows)),
                    "error_m_median_worst": [float(np.median(v)), float(np.max(v))] if (v := figs["error_m"]) else None,
                    "nees_dof_median_worst": [float(np.median(v)), float(np.max(v))]
                    if (v := figs["nees_per_dof"])
                    else None,
                    "outside95": sum(bool(r.get("outside95")) for r in rows),
                }
            ),
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
