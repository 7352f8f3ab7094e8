"""A loop of trajectory calibrations over a family in one process, with padded shapes against exact ones (JSON lines).

    python benchmarks/sweep_shapes.py [--methods nls gp] [--scenario small] [--seeds 0-19] [--drift 0.02]

Each (method, mode) runs in a fresh Python process: `calibrate(simulate(scenario, seed, drift on odd seeds), method)`
for every seed in turn, as a user's sweep or `uncertainty_trajectory.py --family` does. Mode `padded` is the
library's default (`jaxcal.shapes.padded_length`: per-anchor range arrays, the offset fit's arrays, the EM's
thinned ranges and the count of route cells padded so that campaigns of similar size share compiled programs);
mode `exact` runs inside `jaxcal.shapes.exact_lengths()` (the shapes of each campaign exactly, as before). One line
per campaign (wall seconds, XLA compilations and their backend seconds, the anchors' mean 3-D error), then one per
(method, mode) with the totals and one per method with the ratio exact / padded of the wall time and the largest
difference of the estimates between the modes. No persistent compilation cache (the library never enables it).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import numpy as np


def _seeds(text: str) -> list[int]:
    out = []
    for part in filter(None, text.split(",")):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def child(method: str, mode: str, scenario: str, seeds: list[int], drift: float) -> None:
    import contextlib
    import logging

    import jax

    jax.config.update("jax_enable_x64", True)
    logging.getLogger("jaxcal").setLevel(logging.ERROR)
    from jaxcal.methods import calibrate
    from jaxcal.shapes import exact_lengths
    from jaxcal.sim.trajectory import simulate

    count = {"n": 0, "s": 0.0}

    def listen(event, seconds, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            count["n"] += 1
            count["s"] += seconds

    jax.monitoring.register_event_duration_secs_listener(listen)
    ctx = exact_lengths() if mode == "exact" else contextlib.nullcontext()
    with ctx:
        for seed in seeds:
            ds = simulate(scenario, seed=seed, drift=drift if seed % 2 else 0.0)
            n0, s0, t0 = count["n"], count["s"], time.perf_counter()
            res = calibrate(ds, method)
            wall = time.perf_counter() - t0
            err = np.linalg.norm(np.nan_to_num(res.position - ds.anchor_truth), axis=1)
            line = {"method": method, "mode": mode, "seed": seed, "wall_s": round(wall, 3)}
            line.update(compiles=count["n"] - n0, compile_s=round(count["s"] - s0, 3), mean_error_m=float(err.mean()))
            line["position"] = np.asarray(res.position).tolist()
            print(json.dumps(line), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", nargs="+", default=["nls", "gp"])
    ap.add_argument("--scenario", default="small", choices=("small", "campus"))
    ap.add_argument("--seeds", default="0-19")
    ap.add_argument("--drift", type=float, default=0.02, help="pose drift of the odd seeds [m / sqrt(s)]")
    ap.add_argument("--child", nargs=2, metavar=("METHOD", "MODE"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    try:
        seeds = _seeds(args.seeds)
    except ValueError:
        ap.error(f"--seeds {args.seeds!r}: expected e.g. 0-19 or 0,3,7")
    if args.child:
        child(*args.child, args.scenario, seeds, args.drift)
        return 0
    for method in args.methods:
        runs = {}
        for mode in ("padded", "exact"):
            cmd = [sys.executable, __file__, "--child", method, mode, "--scenario", args.scenario]
            cmd += ["--seeds", args.seeds, "--drift", str(args.drift)]
            t0 = time.perf_counter()
            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
            process_s = time.perf_counter() - t0
            lines = [json.loads(x) for x in out.splitlines() if x.startswith("{")]
            for x in lines:
                print(json.dumps({k: v for k, v in x.items() if k != "position"}), flush=True)
            runs[mode] = lines
            total = {"method": method, "mode": mode, "campaigns": len(lines), "process_s": round(process_s, 1)}
            total["wall_s"] = round(sum(x["wall_s"] for x in lines), 1)
            total["wall_after_first_s"] = round(sum(x["wall_s"] for x in lines[1:]), 1)
            total["compiles"] = sum(x["compiles"] for x in lines)
            total["compile_s"] = round(sum(x["compile_s"] for x in lines), 1)
            print(json.dumps(total), flush=True)
        a, b = (np.array([x["position"] for x in runs[m]], dtype=float) for m in ("padded", "exact"))
        summary = {"method": method, "summary": "exact / padded"}
        summary["wall_ratio"] = round(
            sum(x["wall_s"] for x in runs["exact"]) / sum(x["wall_s"] for x in runs["padded"]), 2
        )
        summary["max_position_difference_m"] = float(np.nanmax(np.abs(a - b)))
        summary["same_nan"] = bool((np.isnan(a) == np.isnan(b)).all())
        print(json.dumps(summary), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
