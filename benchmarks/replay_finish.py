"""Replay the last step of a trajectory fit (`jaxcal.trajectory.common.finish`: pose error, flat paths, the mirror
check and its profile) on stored fits, to try values of its parameters on a family without refitting.

    python benchmarks/replay_finish.py cache --method nls --dir DIR [--real] [--scenario small|campus]
        [--family clean|drift] [--seeds 1-19:2]
    python benchmarks/replay_finish.py replay --dir DIR [--set mirror_z=2.131] [--set mirror_profile=0]

`cache` runs `calibrate(dataset, method)` (defaults) on each campaign (`simulate(scenario, seed, drift)` as
`uncertainty_trajectory.py --scenario --family` builds them; campus campaigns are stored as campus-SEED) and on the
shared recordings with `--real`, and pickles the arguments that the method handed to `finish` (one file per campaign
under DIR/METHOD; a file already there is kept).
`replay` runs `finish` again from every file of DIR (with `--set` values replacing the method's), scores it with
`uncertainty_trajectory.py`'s own figures and prints one JSON line per campaign, with the mirror check's decision for
each anchor it checked (z over time stretches, moved, ambiguous, the fit's and the other side's 3-D error), then a
summary per family half (clean-odd, clean-even, drift-odd, drift-even, campus-odd, ...) and per recording. Replayed
without `--set`, the figures are those of `uncertainty_trajectory.py` end to end (the same functions on the same fits).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import pickle
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from uncertainty_trajectory import anchor_figures, line, real_datasets  # noqa: E402

METHOD_MODULES = ("nls", "gp", "gp_anchor", "gp_path", "gp_space", "ls")


def _seeds(text: str) -> list[int]:
    """'1-19:2' -> 1, 3, ..., 19; '0,4,7' -> 0, 4, 7."""
    out = []
    for part in filter(None, text.split(",")):
        span, _, step = part.partition(":")
        a, _, b = span.partition("-")
        out += list(range(int(a), int(b or a) + 1, int(step or 1)))
    return out


def cache(args) -> int:
    import importlib

    from jaxcal.methods import calibrate
    from jaxcal.sim.trajectory import simulate
    from jaxcal.trajectory import common

    out = Path(args.dir) / args.method
    out.mkdir(parents=True, exist_ok=True)
    grabbed = {}

    def grab(dataset, method, p, groups, est, cov, info, solver=None, pose_cov_extra=None):
        import jax

        grabbed["args"] = (dataset, method, p, jax.tree.map(np.asarray, groups), np.asarray(est), np.asarray(cov))
        grabbed["args"] += (info, solver, pose_cov_extra)
        return common.finish(dataset, method, p, groups, est, cov, info, solver, pose_cov_extra)

    for name in METHOD_MODULES:  # the methods import `finish` by name
        mod = importlib.import_module(f"jaxcal.trajectory.{name}")
        if hasattr(mod, "finish"):
            mod.finish = grab
    jobs = list(real_datasets()) if args.real else []
    drift = {"clean": 0.0, "drift": 0.02}[args.family]
    fam = args.family if args.scenario == "small" else args.scenario + ("" if args.family == "clean" else "-drift")
    jobs += [(f"{fam}-{s}", lambda s=s: simulate(args.scenario, seed=s, drift=drift)) for s in _seeds(args.seeds)]
    for label, load in jobs:
        path = out / f"{label}.pkl"
        if path.exists():
            continue
        calibrate(load(), args.method)
        with open(path, "wb") as fh:
            pickle.dump(grabbed["args"], fh)
        print(json.dumps({"cached": str(path)}), flush=True)
    return 0


def _group(name: str) -> str:
    fam, _, seed = name.rpartition("-")
    return f"{fam}-{'odd' if int(seed) % 2 else 'even'}" if seed.isdigit() else name


def replay(args) -> int:
    from jaxcal.trajectory import common, mirror

    overrides = {}
    for kv in args.set:
        k, _, v = kv.partition("=")
        try:
            overrides[k] = json.loads(v)
        except json.JSONDecodeError:
            msg = f"replay_finish.py: --set {kv!r}: expected K=V with V in JSON (e.g. mirror_z=2.131)"
            raise SystemExit(msg) from None
    seen = {}
    compare = mirror.compare_sides

    def keep(*a, **k):  # `finish` imports compare_sides from the module when it runs
        seen["sides"] = compare(*a, **k)
        return seen["sides"]

    mirror.compare_sides = keep
    groups = defaultdict(list)
    files = sorted(Path(args.dir).glob("*/*.pkl"), key=lambda f: (f.parent.name, len(f.stem), f.stem))
    for f in files:
        with open(f, "rb") as fh:
            a = pickle.load(fh)
        ds, est = a[0], a[4]
        if overrides:
            unknown = set(overrides) - {f.name for f in dataclasses.fields(a[2])}
            if unknown:
                raise SystemExit(f"replay_finish.py: --set: {', '.join(sorted(unknown))} not a parameter of {a[1]}")
            a = (a[0], a[1], dataclasses.replace(a[2], **overrides), *a[3:])
        res = common.finish(*a)
        ln = line(f.stem, f.parent.name, anchor_figures(res, ds.anchor_truth))
        ln.pop("worst", None)
        s, truth = seen["sides"], ds.anchor_truth
        ln["decisions"] = [
            {
                "anchor": int(k),
                "z": round(float(s.z[k]), 3),
                "moved": bool(s.moved[k]),
                "ambiguous": bool(s.ambiguous[k]),
                "fit_error_m": round(float(np.linalg.norm(est[k] - truth[k])), 3),
                "other_error_m": round(float(np.linalg.norm((est[k] if s.moved[k] else s.other[k]) - truth[k])), 3),
            }
            for k in np.flatnonzero(s.checked)
        ]
        groups[(f.parent.name, _group(f.stem))].append(ln)
        print(json.dumps(ln), flush=True)
    for (method, group), lines in sorted(groups.items()):
        nees = [x["nees_per_dof"] for x in lines if np.isfinite(x["nees_per_dof"])]
        fixed = [x["fixed_nees_per_dof"] for x in lines if np.isfinite(x["fixed_nees_per_dof"])]
        summary = {
            "summary": group,
            "method": method,
            "set": overrides,
            "campaigns": len(lines),
            "nees_dof_median": float(np.median(nees)) if nees else None,
            "nees_dof_worst": float(np.max(nees)) if nees else None,
            "coverage95_mean": float(np.nanmean([x["coverage95"] for x in lines])),
            "outside95": sum(x["outside95"] for x in lines),
            "fixed_nees_dof_median": float(np.median(fixed)) if fixed else None,
            "nan_heights": sum(x["nan_axes"] for x in lines),
            "mean_error_m": float(np.mean([x["mean_error_m"] for x in lines])),
        }
        print(json.dumps(summary), flush=True)
    return 0


def main(argv=None) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    logging.getLogger("jaxcal").setLevel(logging.ERROR)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("cache", help="fit and store the arguments of finish")
    c.add_argument("--method", default="nls", choices=("nls", "gp", "ls"))
    c.add_argument("--dir", required=True)
    c.add_argument("--real", action="store_true", help="the shared recordings too")
    c.add_argument("--scenario", choices=("small", "campus"), default="small")
    c.add_argument("--family", choices=("clean", "drift"), default="clean")
    c.add_argument("--seeds", default="", help="e.g. 1-19:2 (odd seeds) or 0,2,4")
    r = sub.add_parser("replay", help="run finish again on every stored fit")
    r.add_argument("--dir", required=True)
    r.add_argument("--set", action="append", default=[], metavar="K=V", help="a TrajectoryParams value (JSON)")
    args = ap.parse_args(argv)
    return cache(args) if args.cmd == "cache" else replay(args)


if __name__ == "__main__":
    sys.exit(main())
