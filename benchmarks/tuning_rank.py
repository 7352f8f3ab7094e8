"""Does a no-truth objective rank PGP parameters the way the true RMSE does?

For every scenario and every point of a sigma_r x tau x sigma_v grid, runs the filter as
`jaxcal calibrate` does (`jaxcal.tune_eval`: hard cut, `likelihood="window"`, 0.5 m cells by
default, the whole recording) and records the true RMSE over node-epochs (`rmse_m`, as
`jaxcal.sweep`'s metric of the same name), the filter's own negative log predictive likelihood
(`nlpl`, `jaxcal.sweep`'s `nlpl`) and held-out range errors from the same fold runs:

- `heldout_m`: 4 folds of the pairs among nodes >= 3, each pair scored against its
  10th-percentile range (the candidate figure; not the guard's, docs/benchmarks/tuning.md);
- `heldout2_med_m`: the guard's figure, `tune_eval.heldout_range_error` (2 folds, each pair
  scored against every range, median over epochs of `|z_k - d_k|`);
- `heldout2_m`: 2 folds, 10th-percentile targets (the gradient phase's folds);
- `heldout4_med_m`: 4 folds, every range;
- `consensus_m`: the `consensus` objective's hard figure, `rmse_m` against the robust batch fit
  (`tune_eval.consensus_reference`, `estimate=map`, one fit per scenario) instead of the truth.

`--folds 2` runs only the 2-fold runs (the 4-fold figures are then NaN): 3 filter runs per grid point
instead of 7. The `even` / `odd` sets (development / validation seeds) were added with `consensus_m`;
`dev` / `validation` are the earlier sets.

Prints one JSON line per run, then one per scenario with the Spearman rank correlation of each
objective with the RMSE (higher = ranks like accuracy; lower is better for all objectives) and
the RMSE of each objective's pick, and at the end the median and worst Spearman per objective.

    PYTHONPATH=src python benchmarks/tuning_rank.py [--epochs 300] [--set dev|validation|even|odd|all]
        [--folds 2,4]

(`jaxcal sweep` runs the same grid vmapped on the one-scan path, which evaluates every epoch on
the full grid; on a CPU the chunked fast path of `calibrate`, one run after the other, is faster.)
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import time
import warnings

import numpy as np
from scipy.stats import spearmanr

from jaxcal.mesh import pgp
from jaxcal.sim.mesh import simulate
from jaxcal.tune import truth_in_filter_order, window
from jaxcal.tune_eval import consensus_reference, fold_pair_errors, hard_metrics, hard_run, mean_pair_error, pair_folds

# label, scenario, seed, config, extra params, set; "random": 12 nodes drawn in the torgau hall per
# seed, frame (0, 1, 2). The dev set chose the objective; the validation set only reports it.
SCENARIOS = [
    ("torgau-conf1-s0", "torgau", 0, "conf1", {}, "dev"),
    ("torgau-conf2-s1", "torgau", 1, "conf2", {}, "dev"),
    ("torgau-conf1-s2-mixture", "torgau", 2, "conf1", {"range_model": "mixture"}, "dev"),
    ("small-s0", "small", 0, "conf1", {}, "dev"),
    ("torgau-conf1-s3", "torgau", 3, "conf1", {}, "dev"),
    ("torgau-conf2-s5", "torgau", 5, "conf2", {}, "dev"),
    ("torgau-conf1-s7", "torgau", 7, "conf1", {}, "validation"),
    ("torgau-conf2-s9", "torgau", 9, "conf2", {}, "validation"),
    ("torgau-conf1-s4-mixture", "torgau", 4, "conf1", {"range_model": "mixture"}, "validation"),
    ("torgau-conf2-s8-mixture", "torgau", 8, "conf2", {"range_model": "mixture"}, "validation"),
    ("random-s21", "random", 21, None, {}, "validation"),
    ("random-s22", "random", 22, None, {}, "validation"),
    # development (even) and validation (odd) seeds of the consensus study
    ("torgau-conf1-s10", "torgau", 10, "conf1", {}, "even"),
    ("torgau-conf2-s12", "torgau", 12, "conf2", {}, "even"),
    ("torgau-conf1-s14-mixture", "torgau", 14, "conf1", {"range_model": "mixture"}, "even"),
    ("torgau-conf2-s16-mixture", "torgau", 16, "conf2", {"range_model": "mixture"}, "even"),
    ("random-s30", "random", 30, None, {}, "even"),
    ("random-s32", "random", 32, None, {}, "even"),
    ("torgau-conf1-s11", "torgau", 11, "conf1", {}, "odd"),
    ("torgau-conf2-s13", "torgau", 13, "conf2", {}, "odd"),
    ("torgau-conf1-s15-mixture", "torgau", 15, "conf1", {"range_model": "mixture"}, "odd"),
    ("torgau-conf2-s17-mixture", "torgau", 17, "conf2", {"range_model": "mixture"}, "odd"),
    ("random-s31", "random", 31, None, {}, "odd"),
    ("random-s33", "random", 33, None, {}, "odd"),
]
GRID = {"sigma_r": [0.15, 0.3, 0.8], "tau": [0.6, 0.99], "sigma_v": [0.08, 0.25]}
SCORES = ("nlpl", "heldout_m", "heldout2_m", "heldout4_med_m", "heldout2_med_m", "consensus_m")


def q10_errors(dataset, mask, estimate, order) -> np.ndarray:
    """Per held-out pair, the median over epochs of |q10 - d_k|, q10 the 10th percentile of the
    pair's ranges over the recording (range errors are one-sided; docs/benchmarks/tuning.md)."""
    z = pgp.symmetric_ranges(np.asarray(dataset.range, dtype=np.float64))[:, order][:, :, order]
    est = np.asarray(estimate, dtype=np.float64)
    ii, jj = np.nonzero(np.triu(np.asarray(mask)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # pairs never measured: NaN
        q = np.nanquantile(z[:, ii, jj], 0.1, axis=0)
    e = np.abs(q[None] - np.linalg.norm(est[:, ii] - est[:, jj], axis=-1))
    return np.array([np.median(c[np.isfinite(c)]) if np.isfinite(c).any() else math.nan for c in e.T])


def scores(ds, p, config, folds=(2, 4)) -> dict[str, float]:
    out = {"heldout_m": math.nan, "heldout4_med_m": math.nan}
    for nf in folds:
        new, old = [], []
        for m in pair_folds(ds.n_nodes, nf):
            _, _, run, order = hard_run(ds, p, config, z_mask=m)
            new.append(q10_errors(ds, m, run.estimate, order))
            old.append(fold_pair_errors(ds, m, run.estimate, order))
        # fewer pairs among nodes >= 3 than folds (the 6-node `small` hall with 4): NaN
        out["heldout_m" if nf == 4 else "heldout2_m"] = mean_pair_error(np.concatenate(new or [np.zeros(0)]))
        out[f"heldout{nf}_med_m"] = mean_pair_error(np.concatenate(old or [np.zeros(0)]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--epochs", type=int, default=300)
    ap.add_argument("--cell", type=float, default=0.5)
    ap.add_argument("--set", default="all", choices=["dev", "validation", "even", "odd", "all"])
    ap.add_argument("--folds", default="2,4", help="fold counts of the held-out runs (2,4 or 2)")
    ap.add_argument("--scenarios", default=None, help="comma-separated labels (instead of --set)")
    ap.add_argument("--grid", default=None, help="JSON {name: [values]} replacing grid entries")
    a = ap.parse_args()
    from jaxcal import compile_cache

    compile_cache.enable()  # as the command line: programs compiled once per machine
    scen = [s for s in SCENARIOS if a.set in ("all", s[5])]
    if a.scenarios:
        scen = [s for s in SCENARIOS if s[0] in a.scenarios.split(",")]
    grid = dict(GRID)
    if a.grid:
        grid.update(json.loads(a.grid))
    rhos: dict[str, list[float]] = {k: [] for k in SCORES}
    for label, name, seed, config, extra, _ in scen:
        over = {"positions": None} if name == "random" else {}
        ds = window(simulate("torgau" if name == "random" else name, seed, **over), a.epochs)
        ref = consensus_reference(ds, config)
        rows = []
        for vals in itertools.product(*grid.values()):
            p = {"cell_m": a.cell, **extra, **dict(zip(grid, vals, strict=True))}
            t, c = time.perf_counter(), time.process_time()
            row = {"scenario": label, **dict(zip(grid, vals, strict=True)), **hard_metrics(ds, p, config, ref)}
            row.update(scores(ds, p, config, tuple(int(f) for f in a.folds.split(","))))
            row["seconds"] = round(time.perf_counter() - t, 2)
            row["cpu_seconds"] = round(time.process_time() - c, 2)
            rows.append(row)
            print(json.dumps(row), flush=True)
        r = np.array([x["rmse_m"] for x in rows])
        out = {"scenario": label, "epochs": ds.n_epochs, "runs": len(rows), "loadavg": os.getloadavg()[0]}
        for k in SCORES:
            v = np.array([x[k] for x in rows])
            ok = np.isfinite(v) & np.isfinite(r)
            rho = float(spearmanr(v[ok], r[ok]).statistic) if ok.sum() > 2 else math.nan
            rhos[k].append(rho)
            out[f"spearman_{k}"] = rho
            out[f"rmse_at_best_{k}"] = float(r[int(np.argmin(np.where(ok, v, np.inf)))]) if ok.any() else math.nan
        out["rmse_best"] = float(np.nanmin(r))
        # the pseudo-truth's own error: the batch fit against the truth (a0 excluded)
        tr = truth_in_filter_order(ds, config, np.arange(ds.n_nodes))
        e = np.linalg.norm(ref[1:] - tr[1:], axis=-1)
        out["batch_rmse_m"] = float(np.sqrt(np.nanmean(e**2)))
        out["batch_worst_node_m"] = float(np.nanmax(e))
        out["batch_unplaced"] = int((~np.isfinite(ref).all(-1)).sum())
        print(json.dumps(out), flush=True)
    summary = {
        k: {"median": float(np.nanmedian(v)), "worst": float(np.nanmin(v))}
        for k, v in rhos.items()
        if np.isfinite(v).any()
    }
    print(json.dumps({"scenarios": [s[0] for s in scen], "spearman": summary}), flush=True)


if __name__ == "__main__":
    main()
