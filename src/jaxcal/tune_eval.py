"""Parameters judged the way `jaxcal calibrate` runs them: the hard filter, no gradients.

`tune` checks its start and its end with these (the guard: the tuned values are kept only when they
are better here), and the tuning benchmarks rank parameter sets with them.

- `hard_metrics`: one run of the filter exactly as `calibrate --method pgp` runs it (`pgp.prepare`,
  hard hypothesis cut of eq. 10, `pgp.run_chunked`, the caller's float precision: float32 unless
  64-bit is enabled, as in `calibrate`), reduced to `rmse_m` (every localised (epoch, node)
  estimate against the truth in the configuration frame, a0 excluded: `jaxcal evaluate`'s figure),
  `final_rmse_m`, `availability` and `nlpl` (`tune.neg_log_predictive`: the filter's own
  predictive likelihood of the ranges, nats per range factor).
- `heldout_range_error`: a no-truth score by cross-validation over pairs. The pairs between
  non-anchor nodes (filter order >= 3, so a1 and a2 keep their references of eq. 5-6) are split
  into `n_folds` folds; per fold the filter runs without that fold's ranges and the held-out ranges
  are predicted from the estimates, `|x_i - x_j|`. Score: per held-out pair the median over epochs
  of `|z - |x_i - x_j||` (a median, so the NLOS outliers of a pair do not dominate), averaged over
  pairs and folds [m]. Lower is better. A node placed wrongly (mirrored, or pulled by an outlier
  ring) mispredicts the ranges it was not fitted to; the filter's own predictive likelihood only
  sees ranges it then also conditions on.
- `consensus_reference` / `consensus_m`: a no-truth score against a pseudo-truth, the robust batch
  fit (`jaxcal calibrate --method batch`, `estimate=map`: the most accurate method on these
  networks, needing no truth). `consensus_m` is `rmse_m` with the batch fit's positions in place of
  the truth (same frame, a0 excluded; nodes batch leaves unplaced excluded). Its error against
  `rmse_m` is the batch fit's own error, which does not depend on the filter's parameters.
  `node_sq_errors` splits it by node (mean squared distance from the fit per node), for the
  guard's paired test of two runs (`paired_gain_t`, as the held-out pair errors).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from jaxcal.data import MeshDataset
from jaxcal.mesh import pgp
from jaxcal.params import with_overrides
from jaxcal.tune_metrics import grid_span_m, neg_log_predictive, track_rmse, truth_in_filter_order

__all__ = [
    "hard_run",
    "hard_metrics",
    "hard_metrics_nodes",
    "node_sq_errors",
    "pair_folds",
    "heldout_pair_errors",
    "fold_pair_errors",
    "heldout_split",
    "advance",
    "heldout_range_error",
    "consensus_reference",
]

CONSENSUS_BATCH = {"estimate": "map"}  # the batch fit of the consensus objective (the mode: cheaper)


def _params(params) -> pgp.PGPParams:
    return params if isinstance(params, pgp.PGPParams) else with_overrides(pgp.PGPParams(), params)


def hard_run(dataset: MeshDataset, params, config: str | None, z_mask=None):
    """`calibrate`'s filter run -> (cfg, prm, FilterOut, order); `z_mask` (N, N) bool in filter
    order removes those pairs' ranges (both directions)."""
    p = _params(params)
    cfg, prm, inp, lp0, order = pgp.prepare(dataset, p, config, "pgp")
    if z_mask is not None:
        inp = dataclasses.replace(inp, z=jnp.where(jnp.asarray(z_mask)[None], jnp.nan, inp.z))
    _, out = pgp.run_chunked(cfg, prm, inp, lp0)
    return cfg, prm, out, order


def hard_metrics(dataset: MeshDataset, params, config: str | None, reference=None) -> dict[str, float]:
    """{rmse_m, final_rmse_m, availability, nlpl[, consensus_m]} of one `calibrate` run (module
    docstring); the RMSEs are NaN without ground truth. `reference`: (N, 2) positions in dataset
    order and the configuration frame (`consensus_reference`), scored as `consensus_m`."""
    return hard_metrics_nodes(dataset, params, config, reference)[0]


def hard_metrics_nodes(dataset: MeshDataset, params, config: str | None, reference=None):
    """`hard_metrics` and, with a `reference`, the per-node squared distances behind `consensus_m`
    (`node_sq_errors`, dataset order; None without a reference) of the same run."""
    cfg, prm, out, order = hard_run(dataset, params, config)
    truth = jnp.asarray(truth_in_filter_order(dataset, config, order), out.estimate.dtype)
    est = out.estimate
    have = np.isfinite(np.asarray(est)).all(-1)[:, 1:]
    m = {
        "rmse_m": float(track_rmse(est, truth)),
        "final_rmse_m": float(track_rmse(est[-1:], truth)),
        "availability": float(have.mean()) if have.size else math.nan,
        "nlpl": float(neg_log_predictive(out, prm.sigma_r, prm.p_out, grid_span_m(cfg))),
    }
    nodes = None
    if reference is not None:
        ref = np.asarray(reference)[order]
        m["consensus_m"] = float(track_rmse(est, jnp.asarray(ref, est.dtype)))
        nodes = np.full(len(order), np.nan)
        nodes[order] = node_sq_errors(np.asarray(est), ref)
    return m, nodes


def node_sq_errors(estimate: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per node, the mean over its localised epochs of the squared distance of `estimate`
    (K, N, 2) from `reference` (N, 2) [m^2], same node order; NaN for node 0 (a0, not scored as in
    `track_rmse`), nodes never localised and nodes without a reference position. The guard's
    paired test (`paired_gain_t`) compares two runs node by node with these."""
    est = np.asarray(estimate, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    d2 = np.sum((est - ref[None]) ** 2, axis=-1)  # (K, N); NaN where either is missing
    ok = np.isfinite(d2)
    cnt = ok.sum(0)
    out = np.where(cnt > 0, np.where(ok, d2, 0.0).sum(0) / np.maximum(cnt, 1), np.nan)
    out[:1] = np.nan
    return out


def consensus_reference(dataset: MeshDataset, config: str | None) -> np.ndarray:
    """The consensus objective's pseudo-truth: the robust batch fit (`calibrate --method batch`,
    `CONSENSUS_BATCH`) -> (N, 2) positions [m] in dataset order and the configuration frame (the
    first two axes of a 3-D fit, as `truth_in_filter_order`); NaN rows for nodes it leaves unplaced.
    Raises `JaxcalError` when it places no node besides a0."""
    from jaxcal.errors import JaxcalError
    from jaxcal.methods import calibrate

    res = calibrate(dataset, "batch", CONSENSUS_BATCH, config)
    a0, a1, a2 = dataset.config(config)
    if res.frame_anchors() != (a0, a1, a2):
        raise JaxcalError(f"{dataset.name}: the batch fit's frame {res.frame} is not the configuration's")
    ids = list(res.ids)
    ref = np.full((dataset.n_nodes, 2), np.nan)
    for k, i in enumerate(dataset.node_ids):
        ref[k] = res.position[ids.index(i), :2]
    if np.isfinite(ref).all(-1).sum() < 2:
        raise JaxcalError(f"{dataset.name}: the batch fit placed no node: no consensus reference")
    return ref


def pair_folds(n_nodes: int, n_folds: int = 2, seed: int = 0) -> list[np.ndarray]:
    """Held-out pair masks (N, N) bool in filter order: the pairs among nodes >= 3, shuffled with
    `seed` and dealt into `n_folds` folds (every pair in exactly one fold). Empty when N < 5."""
    pairs = [(i, j) for i in range(3, n_nodes) for j in range(i + 1, n_nodes)]
    if len(pairs) < n_folds:
        return []
    idx = np.random.default_rng(seed).permutation(len(pairs))
    folds = []
    for f in range(n_folds):
        m = np.zeros((n_nodes, n_nodes), dtype=bool)
        for t in idx[f::n_folds]:
            i, j = pairs[t]
            m[i, j] = m[j, i] = True
        folds.append(m)
    return folds


def heldout_pair_errors(
    dataset: MeshDataset, params, config: str | None, n_folds: int = 2, seed: int = 0
) -> np.ndarray:
    """Per held-out pair, the median over epochs of |range - distance of the estimates| [m], in
    the fixed order of `pair_folds` (fold by fold); NaN where the pair has no range or estimate.
    The same order for any parameters, so two runs compare pair by pair (the guard's test)."""
    p = _params(params)
    scores = []
    for m in pair_folds(dataset.n_nodes, n_folds, seed):
        _, _, out, order = hard_run(dataset, p, config, z_mask=m)
        scores.append(fold_pair_errors(dataset, m, out.estimate, order))
    return np.concatenate(scores) if scores else np.zeros(0)


def advance(cfg, prm, inp, st, start: int, stop: int | None = None):
    """Epochs `start:stop` of calibrate's run from state `st` -> (state, FilterOut): the windowed
    fast path (`pgp.advance_chunked`), else one scan (`pgp.run_scan`); either continues exactly."""
    if cfg.window and not cfg.n_snap:
        return pgp.advance_chunked(cfg, prm, inp, st, start, stop)
    stop = int(inp.z.shape[0]) if stop is None else int(stop)
    part = dataclasses.replace(inp, z=inp.z[start:stop], dt=inp.dt[start:stop])
    return pgp.run_scan(cfg, prm, part, st, jnp.asarray(start))


def heldout_split(
    dataset: MeshDataset, params, config: str | None, split: int, n_folds: int = 2, seed: int = 0
) -> tuple[np.ndarray, list]:
    """`heldout_pair_errors`, each fold's run taken in two parts at epoch `split` (the same run),
    and each fold's filter state before epoch `split` (where `tune`'s gradient phase starts).

    Returns:
        (scores as `heldout_pair_errors`, [FilterState per fold]); `split` = 0: initial states.
    """
    p = _params(params)
    cfg, prm, inp, lp0, order = pgp.prepare(dataset, p, config, "pgp")
    scores, states = [], []
    for m in pair_folds(dataset.n_nodes, n_folds, seed):
        fold = dataclasses.replace(inp, z=jnp.where(jnp.asarray(m)[None], jnp.nan, inp.z))
        st = pgp.init_state(cfg, lp0)
        parts = []
        if split > 0:
            st, out = advance(cfg, prm, fold, st, 0, split)
            parts.append(np.asarray(out.estimate))
        states.append(st)
        _, out = advance(cfg, prm, fold, st, split)
        parts.append(np.asarray(out.estimate))
        scores.append(fold_pair_errors(dataset, m, np.concatenate(parts), order))
    return (np.concatenate(scores) if scores else np.zeros(0)), states


def fold_pair_errors(dataset: MeshDataset, mask, estimate, order) -> np.ndarray:
    """`heldout_pair_errors` of one fold: its pairs (`mask`, filter order, upper triangle in
    row-major order) scored on a run without them (`estimate`: (K, N, 2) in filter order)."""
    z = pgp.symmetric_ranges(np.asarray(dataset.range, dtype=np.float64))[:, order][:, :, order]
    est = np.asarray(estimate, dtype=np.float64)
    ii, jj = np.nonzero(np.triu(np.asarray(mask)))
    d = np.linalg.norm(est[:, ii] - est[:, jj], axis=-1)  # (K, P)
    e = np.abs(z[:, ii, jj] - d)
    scores = []
    for c in range(e.shape[1]):
        col = e[:, c][np.isfinite(e[:, c])]
        scores.append(float(np.median(col)) if col.size else math.nan)
    return np.asarray(scores, dtype=np.float64)


def heldout_range_error(dataset: MeshDataset, params, config: str | None, n_folds: int = 2, seed: int = 0) -> float:
    """Cross-validated range error over pairs [m] (module docstring): the mean of
    `heldout_pair_errors`; NaN when no held-out pair has both estimates and a range."""
    return mean_pair_error(heldout_pair_errors(dataset, params, config, n_folds, seed))


def mean_pair_error(scores: np.ndarray) -> float:
    """Mean of the finite per-pair errors of `heldout_pair_errors` [m]; NaN when there is none."""
    scores = np.asarray(scores, dtype=np.float64)
    scores = scores[np.isfinite(scores)]
    return float(np.mean(scores)) if scores.size else math.nan


def paired_gain_t(before: np.ndarray, after: np.ndarray) -> float:
    """t statistic of the per-pair (or per-node, `node_sq_errors`) gain `before - after` (pairs
    finite in both): its mean over its standard error. NaN with fewer than 2 such pairs; +inf when
    every gain is equal and positive."""
    ok = np.isfinite(before) & np.isfinite(after)
    d = np.asarray(before, dtype=np.float64)[ok] - np.asarray(after, dtype=np.float64)[ok]
    if d.size < 2:
        return math.nan
    se = float(np.std(d, ddof=1)) / math.sqrt(d.size)
    if se == 0.0:
        mean = float(np.mean(d))
        return math.inf if mean > 0 else (0.0 if mean == 0 else -math.inf)
    return float(np.mean(d)) / se
