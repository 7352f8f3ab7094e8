"""pgp's mirror check (`jaxcal.mesh.pgp.mirror`) before / after on the networks of `uncertainty_families.py`.

Per network and method the filter runs once with `mirror=off` (the filter's layout as it ends: pgp before the
tenth round); "before" is that result and "after" the mirror check applied to the same filter output
(`mirror.resolve_mirrors`, what `run_pgp` does with the default `mirror=check`), both then through
`with_pair_covariance` and `masking.mask_result` as `calibrate` does. The check runs after the filter, so
one filter run gives both. The filter's results are pickled in `--save` (reused when present: the check
alone is rerun).

Usage:
    python benchmarks/pgp_mirror_families.py --family weak --seeds 0-18 --methods pgp,parametric --save DIR

Prints one JSON line per (network, method, before/after) with the fields of `uncertainty_families.py`
plus `when`, `family` and `check_s` (the check's wall time), then one summary line per (method, when):
well-connected nodes placed, their RMSE and largest error, coverage 95 %, NEES/dof median / worst over the
networks, nodes outside their 95 % ellipse.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import pickle
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
import uncertainty_families as U  # noqa: E402


def row(res, ds, well, seed: int, method: str) -> dict:
    nodes = U.node_figures(res, ds)
    for r in nodes:
        r["well"] = bool(well[r["node"]])
    used = [r for r in nodes if r["well"] and "nees" in r]
    dof = sum(r["dof"] for r in used)
    return {
        "seed": seed,
        "method": method,
        "nees_per_dof": sum(r["nees"] for r in used) / dof if dof else float("nan"),
        "coverage95": float(np.mean([r["inside"] for r in used])) if used else float("nan"),
        "rmse_m": float(np.sqrt(np.mean([r["error_m"] ** 2 for r in used]))) if used else float("nan"),
        "nodes": nodes,
    }


def summary(rows: list[dict]) -> dict:
    nodes = [n for r in rows for n in r["nodes"] if n["well"]]
    placed = [n for n in nodes if "nees" in n]
    err = np.array([n["error_m"] for n in placed])
    nees = [r["nees_per_dof"] for r in rows if np.isfinite(r["nees_per_dof"])]
    return {
        "networks": len(rows),
        "placed": len(placed),
        "well_nodes": len(nodes),
        "rmse_m": float(np.sqrt(np.mean(err**2))) if err.size else float("nan"),
        "max_error_m": float(err.max()) if err.size else float("nan"),
        "coverage95": float(np.mean([n["inside"] for n in placed])) if placed else float("nan"),
        "nees_dof_median": float(np.median(nees)) if nees else float("nan"),
        "nees_dof_worst": float(np.max(nees)) if nees else float("nan"),
        "outside": sum(1 for n in placed if not n["inside"]),
        "weak_placed": sum(1 for r in rows for n in r["nodes"] if not n["well"] and "nees" in n),
    }


def main(argv=None) -> int:
    import equinox as eqx
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxcal.mesh.masking import mask_result
    from jaxcal.mesh.pgp import run_pgp, with_pair_covariance
    from jaxcal.mesh.pgp.mirror import resolve_mirrors

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--family", default="weak", choices=sorted(U.FAMILIES))
    ap.add_argument("--seeds", default="0-9")
    ap.add_argument("--methods", default="pgp,parametric")
    ap.add_argument("--save", required=True, help="folder of the filter's pickled results (reused when present)")
    args = ap.parse_args(argv)
    logging.getLogger("jaxcal").setLevel(logging.ERROR)
    os.makedirs(args.save, exist_ok=True)
    methods = [m for m in args.methods.split(",") if m]
    table: dict = {(m, w): [] for m in methods for w in ("before", "after")}
    for seed in U.parse_seeds(args.seeds):
        ds = U.network(seed, **U.FAMILIES[args.family])
        well = U.rigid_nodes(ds)
        for m in methods:
            path = os.path.join(args.save, f"{args.family}-{seed}-{m}.pkl")
            if os.path.exists(path):
                with open(path, "rb") as f:
                    raw, sec = pickle.load(f)
            else:
                t = time.perf_counter()
                raw = run_pgp(ds, {"mirror": "off"}, "f012", mode=m, posterior=False)[0]
                sec = time.perf_counter() - t
                with open(path, "wb") as f:
                    pickle.dump((raw, sec), f)
            t = time.perf_counter()
            pos, cov = resolve_mirrors(ds.range, ds.node_ids, raw.frame_anchors(), raw.position, raw.covariance, 0.3)
            check_s = time.perf_counter() - t
            after = eqx.tree_at(lambda r: (r.position, r.covariance), raw, (pos, cov))
            for when, res in (("before", raw), ("after", after)):
                out = row(mask_result(with_pair_covariance(res, ds.range), ds.range, warn=False), ds, well, seed, m)
                out.update(when=when, family=args.family, filter_s=round(sec, 2), check_s=round(check_s, 3))
                table[(m, when)].append(out)
                print(json.dumps({k: v for k, v in out.items() if k != "nodes"}), flush=True)
    for (m, when), rows in table.items():
        print(json.dumps({"summary": m, "when": when, "family": args.family, **summary(rows)}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
