"""The guard of `jaxcal.tune`: whether tuned values are kept.

`tune` keeps its optimiser's values only if calibrate's own runs of them beat the start on the hard
figure (`hard_key`); for the no-truth objectives (evidence: held-out pairs; consensus: nodes) the
paired gain of those units must also exceed `GUARD_T` standard errors, pooled over a set of
recordings, and no recording of the set may get clearly worse on its own (`guard_set`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from jaxcal import tune_eval
from jaxcal.data import MeshDataset


def hard_key(objective_name: str, hard_before: dict) -> str:
    """The guard's figure: `rmse_m` for truth, `consensus_m` for consensus; for evidence the
    cross-validated `heldout_m` (the filter's own `nlpl` ranks parameters unlike accuracy,
    docs/benchmarks/tuning.md), or `nlpl` when no pair can be held out (fewer than 5 nodes)."""
    if objective_name == "truth":
        return "rmse_m"
    if objective_name == "consensus":
        return "consensus_m"
    if objective_name == "evidence" and math.isfinite(hard_before.get("heldout_m", math.nan)):
        return "heldout_m"
    return "nlpl"


GUARD_T = 1.0  # no-truth guards: the per-pair / per-node gain must exceed one standard error (t > 1)


def _better(before: float, after: float) -> bool:
    """The guard's plain comparison: `after` finite and lower (or `before` undefined)."""
    return math.isfinite(after) and (not math.isfinite(before) or after < before)


def check(dataset: MeshDataset, params, config: str | None, objective_name: str, reference=None) -> dict:
    """The guard's figures of `params` as `calibrate` runs them (`tune_eval.hard_metrics`, plus
    the cross-validated `heldout_m` for the evidence objective, `consensus_m` against `reference`
    (None: `tune_eval.consensus_reference`) for the consensus objective)."""
    if objective_name == "consensus" and reference is None:
        reference = tune_eval.consensus_reference(dataset, config)
    return _check(dataset, params, config, objective_name, reference=reference)[0]


def _check(dataset, params, config, objective_name, pairs=None, reference=None) -> tuple[dict, np.ndarray | None]:
    """`check` and the units of the guard's paired test: the held-out pair errors for evidence
    (`pairs`: when already measured), the per-node squared distances from `reference` for
    consensus (`tune_eval.node_sq_errors`), else None."""
    m, nodes = tune_eval.hard_metrics_nodes(dataset, params, config, reference)
    if objective_name == "evidence":
        if pairs is None:
            pairs = tune_eval.heldout_pair_errors(dataset, params, config)
        m["heldout_m"] = tune_eval.mean_pair_error(pairs)
        return m, pairs
    return m, nodes


def _guard(before: float, after: float, units_before, units_after) -> tuple[bool, float]:
    """The guard's rule for the no-truth figures (held-out pairs, consensus nodes): `after` better
    (`_better`) and the paired gain of the units beyond `GUARD_T` standard errors
    (`tune_eval.paired_gain_t`; NaN, too few units: the plain comparison) -> (accepted, t)."""
    t = tune_eval.paired_gain_t(units_before, units_after)
    return _better(before, after) and (math.isnan(t) or t > GUARD_T), t


def _mean_dict(ds: list[dict]) -> dict:
    """The recordings' figures averaged key by key (keys every recording has); one: itself."""
    if len(ds) == 1:
        return dict(ds[0])
    return {k: float(np.mean([d[k] for d in ds])) for k in ds[0] if all(k in d for d in ds)}


def guard_set(sets, params, config, objective_name, tuned_params, unmoved, refs, pairs_before, phase) -> dict:
    """The guard over one recording or a set (`tune`'s docstring): calibrate's runs of the start
    and of the tuned values per recording -> {accepted, hard_before, hard_after (the means),
    t (pooled), recordings (each one's figures and t), worse (name of a recording whose own
    t < -GUARD_T, else "")}."""
    before: list[dict] = []
    units_b: list[Any] = []
    for i, d in enumerate(sets):
        phase("guard: calibrate's runs of the start", i)
        m, u = _check(d, params, config, objective_name, pairs_before[i], refs[i])
        before.append(m)
        units_b.append(u)
    hb = _mean_dict(before)
    key = hard_key(objective_name, hb)
    after: list[dict] = [dict(m) for m in before]
    t, own, worse, accepted = math.nan, [math.nan] * len(sets), "", False
    if not unmoved:  # the optimiser moved: run the tuned values
        units_a: list[Any] = []
        for i, d in enumerate(sets):
            phase("guard: calibrate's runs of the tuned values", i)
            if key == "heldout_m":
                pairs_after = tune_eval.heldout_pair_errors(d, tuned_params, config)
                after[i] = {"heldout_m": tune_eval.mean_pair_error(pairs_after)}
                units_a.append(pairs_after)
            elif key == "consensus_m":
                after[i], nodes_after = _check(d, tuned_params, config, objective_name, reference=refs[i])
                units_a.append(nodes_after)
            else:
                after[i] = check(d, tuned_params, config, objective_name, refs[i])
        if units_a:
            # a gain within the pairs' / nodes' own scatter is noise (measured: accepted gains of 1e-4 m
            # came with 1-2.5 % worse RMSE; 2 % closer to the batch fit was 5 % further from the truth):
            # the pooled per-unit gain must exceed one standard error, and no recording clearly lose
            accepted, t = _guard(hb[key], _mean_dict(after)[key], np.concatenate(units_b), np.concatenate(units_a))
            own = [tune_eval.paired_gain_t(b, a) for b, a in zip(units_b, units_a, strict=True)]
            unique = len({d.name for d in sets}) == len(sets)  # else say which one by its place
            bad = [
                d.name if unique else f"recording {i + 1} ({d.name})"
                for i, (d, ti) in enumerate(zip(sets, own, strict=True))
                if ti < -GUARD_T
            ]
            worse = bad[0] if bad else ""
            accepted = accepted and not bad
            if accepted and key == "heldout_m":  # calibrate's plain run of the values written
                after = [
                    {**tune_eval.hard_metrics(d, tuned_params, config), **a} for d, a in zip(sets, after, strict=True)
                ]
        else:
            accepted = _better(hb[key], _mean_dict(after)[key])
    recordings = [
        {"dataset": d.name, "epochs": d.n_epochs, "hard_before": b, "hard_after": a, "guard_gain_t": ti}
        for d, b, a, ti in zip(sets, before, after, own, strict=True)
    ]
    return {
        "accepted": accepted,
        "hard_before": hb,
        "hard_after": _mean_dict(after),
        "t": t,
        "recordings": recordings,
        "worse": worse,
    }
