"""Does a no-truth objective rank PGP parameters the way the true RMSE does?

For every scenario and every point of a sigma_r x tau x sigma_v grid, runs the filter as
`jaxcal calibrate` does (`jaxcal.tune_eval`: hard cut, `likelihood="window"`, 0.5 m cells by
default, the whole recording) and records the true RMSE over node-epochs (`rmse_m`, as
`jaxcal.sweep`'s metric of the same name), the filter's own negative log predictive likelihood
(`nlpl`, `jaxcal.sweep`'s `nlpl`) and the cross-validated held-out range error (`heldout_m`).
Prints one JSON line per run, then one per scenario with the Spearman rank correlation of each
objective with the RMSE (higher = ranks like accuracy; lower objective is better for both).

    PYTHONPATH=src python benchmarks/tuning_rank.py [--epochs 1000] [--quick]

(`jaxcal sweep` runs the same grid vmapped on the one-scan path, which evaluates every epoch on
the full grid; on a CPU the chunked fast path of `calibrate`, one run after the other, is faster.)
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import time

import numpy as np
from scipy.stats import spearmanr

from jaxcal.sim.mesh import simulate
from jaxcal.tune import window
from jaxcal.tune_eval import hard_metrics, heldout_range_error

SCENARIOS = [  # label, scenario, seed, config, extra params
    ("torgau-conf1-s0", "torgau", 0, "conf1", {}),
    ("torgau-conf2-s1", "torgau", 1, "conf2", {}),
    ("torgau-conf1-s2-mixture", "torgau", 2, "conf1", {"range_model": "mixture"}),
    ("small-s0", "small", 0, "conf1", {}),
    ("torgau-conf1-s3", "torgau", 3, "conf1", {}),
    ("torgau-conf2-s5", "torgau", 5, "conf2", {}),
]
GRID = {"sigma_r": [0.15, 0.3, 0.8], "tau": [0.6, 0.9, 0.99], "sigma_v": [0.08, 0.25, 0.8]}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--epochs", type=int, default=1000)
    ap.add_argument("--cell", type=float, default=0.5)
    ap.add_argument("--folds", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="two scenarios, 2 x 2 x 2 grid")
    ap.add_argument("--scenarios", default=None, help="comma-separated labels (default: the first 4)")
    ap.add_argument(
        "--grid", default=None, help="JSON {name: [values]} replacing the grid, e.g. '{\"sigma_v\": [0.08]}'"
    )
    a = ap.parse_args()
    from jaxcal import compile_cache

    compile_cache.enable()  # as the command line: programs compiled once per machine
    scen = SCENARIOS[:1] + SCENARIOS[3:4] if a.quick else SCENARIOS[:4]
    if a.scenarios:
        scen = [s for s in SCENARIOS if s[0] in a.scenarios.split(",")]
    grid = {k: v[:1] + v[2:] for k, v in GRID.items()} if a.quick else dict(GRID)
    if a.grid:
        grid.update(json.loads(a.grid))
    for label, name, seed, config, extra in scen:
        ds = window(simulate(name, seed), a.epochs)
        rows = []
        for vals in itertools.product(*grid.values()):
            p = {"cell_m": a.cell, **extra, **dict(zip(grid, vals, strict=True))}
            t = time.perf_counter()
            m = hard_metrics(ds, p, config)
            m["heldout_m"] = heldout_range_error(ds, p, config, n_folds=a.folds)
            row = {
                "scenario": label,
                **dict(zip(grid, vals, strict=True)),
                **m,
                "seconds": round(time.perf_counter() - t, 2),
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
        r = np.array([x["rmse_m"] for x in rows])
        out = {
            "scenario": label,
            "epochs": ds.n_epochs,
            "cell_m": a.cell,
            "runs": len(rows),
            "loadavg": os.getloadavg()[0],
        }
        for k in ("nlpl", "heldout_m"):
            v = np.array([x[k] for x in rows])
            ok = np.isfinite(v) & np.isfinite(r)
            rho = spearmanr(v[ok], r[ok]).statistic if ok.sum() > 2 else None
            out[f"spearman_{k}"] = None if rho is None else float(rho)
            best = int(np.nanargmin(np.where(ok, v, np.inf)))
            out[f"rmse_at_best_{k}"] = float(r[best])
        out["rmse_best"] = float(np.nanmin(r))
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
