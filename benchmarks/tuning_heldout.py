"""Held-out proof of `jaxcal tune`: tune on one dataset, calibrate others with the result.

Simulated families (tune on the first seed, or with `--train N` on the set of the first N seeds,
report on the others; no truth used by `evidence`):

- torgau-conf1: the torgau hall (Table-I-shaped errors, NLOS walls, outlier pairs), frame conf1;
- torgau-conf2: the same hall, frame conf2;
- torgau-mixture: conf1 with the NLOS-aware mixture range kernel (`range_model="mixture"`, whose
  nlos_weight and nlos_mean_m are tuned too);
- random-layout: 12 nodes drawn uniformly in the torgau hall per seed (every seed a new layout),
  frame (0, 1, 2): tuned on one layout, reported on others.

Real: the three dwm1001-autocal scenarios in ../shared/datasets (skipped when absent): tuning on
the recording itself with `--objective` (evidence or consensus: no truth needed; `truth` falls back
to evidence there), the truth only for the RMSE; the
gradient phase on the same `--tune-epochs` / `--tune-cell` as the simulated families.

Per row: RMSE over localised node-epochs (a0 excluded, configuration frame; `jaxcal evaluate`'s
figure) of `calibrate`'s run with the defaults and with the params `tune` returned (after its
guard). One JSON line per row, then a Markdown table and the summary (median ratio, worst ratio).

    PYTHONPATH=src python benchmarks/tuning_heldout.py [--epochs 2000] [--tune-epochs K]
        [--tune-cell M] [--max-steps S] [--objective evidence] [--families a,b] [--no-real]
        [--real srvlab_ground,...] [--seed-offset 100] [--train N] [--tests N]

`--seed-offset` shifts every seed of the families (train and test) to draw recordings no table of
docs/benchmarks/tuning.md has used (those use seeds below 50).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from jaxcal.sim.mesh import simulate
from jaxcal.tune import tune, window
from jaxcal.tune_eval import hard_metrics

ROOT = Path(__file__).resolve().parents[1]
DWM = ROOT.parent / "shared" / "datasets" / "dwm1001-autocal"
REAL = [
    ("campus_sport/rich_samples", "campus_sport"),
    ("srvlab_ground", "srvlab_ground"),
    ("3D_distribution", "3D_distribution"),
]
# family: (scenario, config, fixed params, overrides, train seed, test seeds); the first 4 test
# seeds are those of the earlier tables, the next 4 were added with the consensus objective
FAMILIES = {
    "torgau-conf1": ("torgau", "conf1", {}, {}, 0, [3, 4, 13, 14, 23, 24, 33, 34]),
    "torgau-conf2": ("torgau", "conf2", {}, {}, 1, [5, 6, 15, 16, 25, 26, 35, 36]),
    "torgau-mixture": ("torgau", "conf1", {"range_model": "mixture"}, {}, 2, [7, 8, 17, 18, 27, 28, 37, 38]),
    "random-layout": ("torgau", None, {}, {"positions": None}, 10, [11, 12, 19, 20, 29, 40, 41, 42]),
}


def sim(name, seed, overrides, epochs):
    return window(simulate(name, seed, **overrides), epochs)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--epochs", type=int, default=2000, help="epochs of every simulated dataset")
    ap.add_argument("--tune-epochs", type=int, default=None)
    ap.add_argument("--tune-cell", type=float, default=None)
    ap.add_argument("--max-steps", type=int, default=12)
    ap.add_argument("--objective", default="evidence")
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--no-real", action="store_true")
    ap.add_argument("--tests", type=int, default=2, help="test seeds per family (train + tests at most 9)")
    ap.add_argument(
        "--train", type=int, default=1, help="tune on a set of the family's first N seeds (`tune`'s mean objective)"
    )
    ap.add_argument("--real-first", action="store_true", help="the dwm1001 rows before the families")
    ap.add_argument("--real", default=",".join(c for _, c in REAL), help="which dwm1001 scenarios")
    ap.add_argument("--seed-offset", type=int, default=0, help="added to every train and test seed (new seeds: >= 100)")
    a = ap.parse_args()
    from jaxcal import compile_cache

    compile_cache.enable()  # as the command line: programs compiled once per machine
    rows = []

    def emit(row):
        row["loadavg"] = round(os.getloadavg()[0], 1)
        rows.append(row)
        print(json.dumps(row), flush=True)

    def real():
        if a.no_real or not DWM.is_dir():
            return
        from jaxcal.io.importers import import_recording

        for folder, cfg in [r for r in REAL if r[1] in a.real.split(",")]:
            yaml_path = DWM / "nodes_cfg" / f"{cfg}.yaml"
            ds = import_recording("dwm1001-autocal", DWM / folder, yaml_path)
            t, c = time.perf_counter(), time.process_time()
            res = tune(
                ds,
                {},
                "conf1",
                objective_name="evidence" if a.objective == "truth" else a.objective,
                epochs=a.tune_epochs,
                cell_m=a.tune_cell,
                max_steps=a.max_steps,
            )
            emit(
                {
                    "family": f"dwm1001/{cfg}",
                    "role": "self",
                    "seed": -1,
                    "accepted": res.accepted,
                    "start": res.start,
                    "tuned": res.tuned,
                    "rmse_default_m": res.hard_before["rmse_m"],
                    "rmse_tuned_m": (res.hard_after if res.accepted else res.hard_before)["rmse_m"],
                    "guard_key": res.hard_key,
                    "guard_default": res.hard_before.get(res.hard_key),
                    "guard_tuned": res.hard_after.get(res.hard_key),
                    "steps": res.steps,
                    "message": res.message,
                    "guard_gain_t": res.settings["guard_gain_t"],
                    "seconds": round(time.perf_counter() - t, 1),
                    "cpu_seconds": round(time.process_time() - c, 1),
                }
            )

    if a.real_first:
        real()
    for fam in [f for f in a.families.split(",") if f]:
        name, config, fixed, over, train, tests = FAMILIES[fam]
        seeds = [s + a.seed_offset for s in [train, *tests]]
        trains, tests = seeds[: a.train], seeds[a.train : a.train + a.tests]
        t, c = time.perf_counter(), time.process_time()
        res = tune(
            [sim(name, s, over, a.epochs) for s in trains] if a.train > 1 else sim(name, trains[0], over, a.epochs),
            fixed,
            config,
            objective_name=a.objective,
            epochs=a.tune_epochs,
            cell_m=a.tune_cell,
            max_steps=a.max_steps,
        )
        recs = res.settings["recordings"]
        for k, (s, rec) in enumerate(zip(trains, recs, strict=True)):
            kept = rec["hard_after"] if res.accepted else rec["hard_before"]
            emit(
                {
                    "family": fam,
                    "role": "train",
                    "seed": s,
                    "accepted": res.accepted,
                    "rmse_default_m": rec["hard_before"]["rmse_m"],
                    "rmse_tuned_m": kept["rmse_m"],
                    "guard_key": res.hard_key,
                    "guard_default": rec["hard_before"].get(res.hard_key),
                    "guard_tuned": rec["hard_after"].get(res.hard_key),
                    "guard_gain_t_own": rec["guard_gain_t"],
                    **(
                        {}
                        if k
                        else {  # the set's tuning, on its first row
                            "train_seeds": trains,
                            "start": res.start,
                            "tuned": res.tuned,
                            "steps": res.steps,
                            "message": res.message,
                            "guard_gain_t": res.settings["guard_gain_t"],
                            "worse_recording": res.settings["worse_recording"],
                            "guard_default_mean": res.hard_before.get(res.hard_key),
                            "guard_tuned_mean": res.hard_after.get(res.hard_key),
                            "grad_epochs": res.settings["epochs"],
                            "grad_cell_m": res.settings["cell_m"],
                            "seconds": round(time.perf_counter() - t, 1),
                            "cpu_seconds": round(time.process_time() - c, 1),
                            "seconds_gradient_phase": round(res.seconds["tune"], 1),
                        }
                    ),
                }
            )
        for s in tests:
            ds = sim(name, s, over, a.epochs)
            d = hard_metrics(ds, fixed, config)
            u = d if not res.accepted else hard_metrics(ds, {**fixed, **res.params}, config)
            emit(
                {
                    "family": fam,
                    "role": "test",
                    "seed": s,
                    "accepted": res.accepted,
                    "rmse_default_m": d["rmse_m"],
                    "rmse_tuned_m": u["rmse_m"],
                    "nlpl_default": d["nlpl"],
                    "nlpl_tuned": u["nlpl"],
                }
            )
    if not a.real_first:
        real()
    ev = [r for r in rows if "rmse_default_m" in r]
    print(f"\n<!-- {platform.node()} {os.cpu_count()} cpus, args {vars(a)} -->")
    print("| family | role | seed | tuned values kept | RMSE defaults [m] | RMSE after tune [m] | ratio |")
    print("|---|---|---|---|---|---|---|")
    for r in ev:
        ratio = r["rmse_tuned_m"] / r["rmse_default_m"]
        r["ratio"] = ratio
        print(
            f"| {r['family']} | {r['role']} | {r['seed']} | {'yes' if r['accepted'] else 'no'} "
            f"| {r['rmse_default_m']:.3f} | {r['rmse_tuned_m']:.3f} | {ratio:.3f} |"
        )
    for label, sel in (("all rows", ev), ("held-out (test) rows", [r for r in ev if r["role"] == "test"])):
        if not sel:
            continue
        d = np.array([r["rmse_default_m"] for r in sel])
        u = np.array([r["rmse_tuned_m"] for r in sel])
        print(
            json.dumps(
                {
                    "rows": label,
                    "n": len(sel),
                    "median_default_m": float(np.median(d)),
                    "median_tuned_m": float(np.median(u)),
                    "worst_ratio": float(np.max(u / d)),
                    "best_ratio": float(np.min(u / d)),
                }
            )
        )


if __name__ == "__main__":
    main()
