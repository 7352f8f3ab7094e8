"""Differentiable tuning of the PGP filter's sigma_r, sigma_v and tau (Optimistix BFGS, scan).

The filter of `jaxcal.mesh.pgp` is differentiable in its numeric parameters except for the hard
hypothesis cut of eq. (10), whose derivative in `tau` is zero almost everywhere. Tuning thus runs
the filter with `select="soft"`: cell l of a node's sorted cells is weighted by
`sigmoid((tau - m_l) / tau_temp)`, `m_l` the probability mass before it (`grid.soft_hypotheses`; the
hard rule is the limit `tau_temp -> 0`). The parameters are optimised unconstrained as
`theta = (log sigma_r, log sigma_v, logit tau)`, and with `range_model="mixture"` also
`(logit nlos_weight, log nlos_mean_m)` of the NLOS-aware range kernel (`grid.range_kernel_log`).

Objectives (over the tuning data, by default the whole dataset):

- `truth`: RMSE [m] of the final positions (a0 excluded) against the ground truth in the
  configuration frame, each position the tempered eq. (13) estimate of `soft_estimates` (a grid
  posterior collapses into one cell, where eq. 13 itself is piecewise constant: zero gradient).
- `evidence` (the default; no ground truth): cross-validation over pairs. The pairs between
  non-anchor nodes are dealt into two folds (`tune_eval.pair_folds`); per fold the filter runs
  without that fold's ranges, and the loss is the mean over the fold's pairs of
  `sqrt(r^2 + 0.05^2)`, `r = median_k z_ij - |x_i - x_j|` (the pair's median range against the
  distance of the final tempered estimates, as in `truth`); the folds' losses are averaged [m].
  A node placed wrongly mispredicts the ranges it was not fitted to. The hard counterpart that the
  guard compares is `tune_eval.heldout_range_error`. Datasets with fewer than 5 nodes have no pair
  to hold out: `evidence` then falls back to `nlpl` (and says so in `TuneResult.settings`).
- `consensus` (no ground truth): `truth` with the robust batch fit's positions in place of the truth
  (`tune_eval.consensus_reference`: `calibrate --method batch`, `estimate=map`, of the whole
  dataset, in the configuration frame; nodes it leaves unplaced do not count). The batch fit is
  the most accurate method on these networks, so the objective's error against the true RMSE is
  the batch fit's own, which does not depend on the filter's parameters. Its hard counterpart
  (the guard) is `consensus_m` of `tune_eval.hard_metrics`: calibrate's track RMSE against the fit.
  It ranks parameter sets like the true RMSE where `evidence` does not (docs/benchmarks/tuning.md,
  section 1: Spearman median +0.84 against -0.29 on validation seeds), but BFGS on it also fits
  the batch fit's own errors: on the mixture family a plain guard accepted a 2 % lower
  `consensus_m` that was a 5 % higher true RMSE (section 2). The guard therefore asks, as for
  `evidence`, that the per-node gain (`tune_eval.node_sq_errors`) exceed one standard error. Without a batch fit (it
  raises) `tune` falls back to `evidence` (`settings["fallback_reason"]`).
- `nlpl`: negative log predictive likelihood of the measured ranges, in nats per range factor.
  Per epoch and node, before the update, the log normaliser of eq. (12), `log sum_g pbar(g) L(g)`
  (`FilterOut.log_evidence`), with each eq. (11) factor read as a density of the range z on [0, L]:
  `f(z | g) = ((1 - p_out) sum_l w_l exp(-(|g - g_l| - z)^2 / 2 sigma_r^2) + p_out) / Z`,
  `Z = (1 - p_out) sigma_r sqrt(2 pi) + p_out L`, L = the grid's diagonal (the longest range it
  can explain). This is the filter's own factor up to a constant in z, so the filter's posterior is
  exactly the one this density model implies; with `p_out = 0` it is the Gaussian of eq. (11). The
  mixture kernel is scaled to the same integral `sigma_r sqrt(2 pi)`, so Z holds for it too. No
  ground truth is needed. (Nodes update independently given the others' hypotheses, so the sum over
  nodes is a pseudo-likelihood; every pair's range enters once per end.) It ranks parameters
  unlike accuracy (it prefers a wide sigma_r that explains the NLOS excess; docs/benchmarks/
  tuning.md), hence not the default.

Memory: the scan runs in checkpointed segments (`mesh.segmented`): reverse mode keeps ~2 sqrt(K)
`(nodes, cells)` carries instead of K, every epoch recomputed in the backward pass. float64.

Guard (`tune`): the start and the tuned values are run as `calibrate` runs them (hard cut, its
cell size and likelihood path, the whole dataset); the tuned values are kept only if better. With
the no-truth figures, better means beyond the units' own scatter: the per-pair gain of the held-out
ranges (`evidence`) or the per-node gain of the squared distance from the batch fit (`consensus`)
(`tune_eval.paired_gain_t`) must exceed `GUARD_T` (1) standard errors, so a gain of noise size keeps
the start (`settings["guard_gain_t"]` records the t).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable, Sequence
from typing import Any, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from jaxcal import tune_eval
from jaxcal.data import MeshDataset
from jaxcal.errors import JaxcalError
from jaxcal.mesh import grid as G
from jaxcal.mesh import pgp
from jaxcal.mesh.segmented import filter_segmented, segment_length
from jaxcal.params import with_overrides
from jaxcal.progress import ProgressCallback
from jaxcal.tune_guard import GUARD_T, guard_set, hard_key
from jaxcal.tune_metrics import (
    final_rmse,
    grid_span_m,
    neg_log_predictive,
    track_rmse,
    truth_in_filter_order,
    window,
)

__all__ = [
    "OBJECTIVES",
    "TUNED",
    "TuneResult",
    "window",
    "truth_in_filter_order",
    "track_rmse",
    "final_rmse",
    "neg_log_predictive",
    "grid_span_m",
    "Problem",
    "make_problem",
    "objective",
    "tune",
]

OBJECTIVES = ("evidence", "truth", "nlpl", "consensus")
HELDOUT_EPS_M = 0.05  # smooths |r| at 0 (gradient) in the evidence loss
TUNED = ("sigma_r", "sigma_v", "tau")
# tuned as well when range_model="mixture" (theta entries 3 and 4)
TUNED_MIXTURE = ("nlos_weight", "nlos_mean_m")
_LOGIT = ("tau", "nlos_weight")  # in (0, 1); the others are positive (log)


def tuned_names(range_model: str) -> tuple[str, ...]:
    """Names of theta's entries, in order, for a range model."""
    return TUNED + (TUNED_MIXTURE if range_model == "mixture" else ())


class Problem(eqx.Module):
    """Everything the objective needs besides theta (the filter's config is static)."""

    cfg: pgp.FilterConfig
    prm: pgp.FilterParams
    inp: pgp.FilterInputs
    logpost0: Float[Array, "nodes nx ny"]
    truth: Float[Array, "nodes 2"]
    est_temp: Float[Array, ""]
    span_m: float = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    segment: int = eqx.field(static=True, default=0)  # epochs per checkpointed segment (0: sqrt)
    folds: Array | None = None  # (F, N, N) bool held-out pairs (evidence)
    targets: Float[Array, "nodes nodes"] | None = None  # median range per pair [m] (evidence)
    # the filter state before `inp`'s first epoch (None: the initial state), one per fold for
    # evidence (stacked): the tail gradient phase (`tune(tail=...)`) starts from calibrate's run
    state: pgp.FilterState | None = None
    k0: int = eqx.field(static=True, default=0)  # index of `inp`'s first epoch in the recording


def make_problem(
    dataset: MeshDataset,
    params: pgp.PGPParams,
    config: str | None,
    kind: str,
    tau_temp: float = 0.05,
    remat: bool = True,
    est_temp: float = 10.0,
    segment: int | None = None,
    tail_from: int = 0,
    states=None,
    reference: np.ndarray | None = None,
) -> tuple[Problem, np.ndarray]:
    """Prepare the filter for tuning (soft hypothesis cut, rematerialised epochs).

    Args:
        dataset: the (windowed) mesh dataset. params: filter parameters (the start point).
        config: frame configuration name. kind: one of `OBJECTIVES`.
        tau_temp: temperature of the soft cut (mass units; 0 gives the hard rule, not differentiable
            in tau). remat: checkpoint every epoch (memory ~ epochs x carry).
        est_temp: temperature of the `truth` objective's estimate (`soft_estimates`, nats).
        segment: epochs per checkpointed segment of the scan (None: `segment_length(epochs)`).
        tail_from, states: differentiate only epochs `tail_from:` of the dataset, from these
            filter states before epoch `tail_from` (one per fold for evidence, in `pair_folds`'
            order, else one; e.g. `tune_eval.heldout_split`'s); float arrays are cast to the
            problem's dtype. The evidence targets are the whole dataset's.
        reference: the consensus objective's pseudo-truth, (N, 2) in dataset order and the
            configuration frame (None: `tune_eval.consensus_reference` of `dataset`).

    Returns:
        (Problem, order): `order[k]` is the dataset index of filter node k.
    """
    if kind not in OBJECTIVES:
        raise JaxcalError(f"objective: one of {', '.join(OBJECTIVES)}; got {kind!r}")
    cfg, prm, inp, lp0, order = pgp.prepare(dataset, params, config, "pgp")
    ftype = lp0.dtype
    select = "soft" if tau_temp > 0 else "hard"
    cfg = dataclasses.replace(cfg, select=select, remat=remat)
    prm = dataclasses.replace(prm, tau_temp=jnp.asarray(max(tau_temp, 1e-12), ftype))
    if kind == "consensus":
        ref = tune_eval.consensus_reference(dataset, config) if reference is None else np.asarray(reference)
        truth = ref[order]
    else:
        truth = truth_in_filter_order(dataset, config, order)
    if kind == "truth" and not np.isfinite(truth[1:]).any():
        raise JaxcalError(f"{dataset.name}: objective 'truth' needs ground truth (use --objective evidence)")
    folds = targets = None
    if kind == "evidence":
        fl = tune_eval.pair_folds(dataset.n_nodes)
        if not fl:
            kind = "nlpl"  # fewer than 5 nodes: no pair to hold out
        else:
            folds = jnp.asarray(np.stack(fl))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # pairs never measured: NaN
                targets = jnp.asarray(np.nanmedian(np.asarray(inp.z, np.float64), axis=0), ftype)
    state = None
    if tail_from:
        if states is None or len(states) != (len(folds) if folds is not None else 1):
            raise ValueError("make_problem: tail_from needs one start state per fold (or one)")
        inp = dataclasses.replace(inp, z=inp.z[tail_from:], dt=inp.dt[tail_from:])
        cast = [
            jax.tree.map(lambda a: a.astype(ftype) if jnp.issubdtype(a.dtype, jnp.floating) else a, st) for st in states
        ]
        state = jax.tree.map(lambda *a: jnp.stack(a), *cast) if folds is not None else cast[0]
    prob = Problem(
        cfg,
        prm,
        inp,
        lp0,
        jnp.asarray(truth, ftype),
        jnp.asarray(est_temp, ftype),
        grid_span_m(cfg),
        kind,
        int(segment or 0),
        folds,
        targets,
        state,
        int(tail_from),
    )
    return prob, order


def _with_theta(prm: pgp.FilterParams, theta: Float[Array, " p"]) -> pgp.FilterParams:
    names = (TUNED + TUNED_MIXTURE)[: theta.shape[0]]
    return dataclasses.replace(
        prm,
        **{k: jax.nn.sigmoid(theta[i]) if k in _LOGIT else jnp.exp(theta[i]) for i, k in enumerate(names)},
    )


def theta_of(
    sigma_r: float,
    sigma_v: float,
    tau: float,
    dtype=None,
    nlos_weight: float | None = None,
    nlos_mean_m: float | None = None,
) -> Float[Array, " p"]:
    """Unconstrained parameters (log sigma_r, log sigma_v, logit tau[, logit nlos_weight,
    log nlos_mean_m]); the last two only when `nlos_weight` is given."""

    def logit(u):
        u = min(max(u, 1e-6), 1 - 1e-6)
        return math.log(u / (1 - u))

    t = [math.log(sigma_r), math.log(sigma_v), logit(tau)]
    if nlos_weight is not None:
        assert nlos_mean_m is not None, "nlos_mean_m goes with nlos_weight"
        t += [logit(nlos_weight), math.log(nlos_mean_m)]
    return jnp.asarray(t, dtype)


def values_of(theta) -> dict[str, float]:
    """{sigma_r, sigma_v, tau[, nlos_weight, nlos_mean_m]} of unconstrained parameters."""
    t = np.asarray(theta, dtype=np.float64)
    names = (TUNED + TUNED_MIXTURE)[: t.shape[0]]
    return {k: float(1.0 / (1.0 + np.exp(-t[i])) if k in _LOGIT else np.exp(t[i])) for i, k in enumerate(names)}


def objective(theta: Float[Array, " p"], prob: Problem | tuple[Problem, ...]) -> Float[Array, ""]:
    """Objective at theta (`theta_of`): held-out range loss [m], RMSE [m] (against the truth or the
    consensus reference) or NLPL [nats]; of a tuple of problems (a set of recordings, the same
    kind), the mean of theirs."""
    if isinstance(prob, tuple):
        total = objective(theta, prob[0])
        for p in prob[1:]:
            total = total + objective(theta, p)
        return total / len(prob)
    prm = _with_theta(prob.prm, theta)
    if prob.kind == "evidence":
        return _heldout_loss(prm, prob)
    st, out = filter_segmented(prob.cfg, prm, prob.inp, prob.logpost0, prob.segment or None, prob.state, prob.k0)
    if prob.kind in ("truth", "consensus"):  # consensus: the batch fit is `prob.truth`
        return final_rmse(_final_estimates(st, out, prm, prob)[None], prob.truth)
    return neg_log_predictive(out, prm.sigma_r, prm.p_out, prob.span_m)


def _final_estimates(st, out, prm, prob: Problem):
    """Tempered eq. (13) final positions (N, 2); NaN for nodes not localised."""
    radius = jnp.maximum(prm.r_est, 1.5 * prob.cfg.grid.cell_m)
    est = soft_estimates(st.logpost, prob.cfg.grid.cells(st.logpost.dtype), radius, prob.est_temp)
    loc = jnp.isfinite(out.estimate[-1]).all(-1)
    return jnp.where(loc[:, None], est, jnp.nan)


def _heldout_loss(prm: pgp.FilterParams, prob: Problem) -> Float[Array, ""]:
    """The evidence objective (module docstring): per fold, run without its pairs, predict them."""

    def fold(x):
        m, st0 = x
        inp = dataclasses.replace(prob.inp, z=jnp.where(m[None], jnp.nan, prob.inp.z))
        st, out = filter_segmented(prob.cfg, prm, inp, prob.logpost0, prob.segment or None, st0, prob.k0)
        est = _final_estimates(st, out, prm, prob)
        ok = jnp.triu(m, 1) & jnp.isfinite(prob.targets) & jnp.isfinite(est).all(-1)[:, None]
        ok = ok & jnp.isfinite(est).all(-1)[None, :]
        e = jnp.where(jnp.isfinite(est), est, 0.0)
        d = G.safe_norm(e[:, None, :] - e[None, :, :])
        r = jnp.where(ok, jnp.where(ok, prob.targets, 0.0) - d, 0.0)
        loss = jnp.where(ok, jnp.sqrt(r * r + HELDOUT_EPS_M**2), 0.0)
        return jnp.sum(loss), jnp.sum(ok)

    total, count = jax.lax.map(fold, (prob.folds, prob.state))
    n = jnp.sum(count)
    return jnp.where(n > 0, jnp.sum(total) / jnp.maximum(n, 1), jnp.nan)


def soft_estimates(
    logpost: Float[Array, "nodes nx ny"], cells: Float[Array, "cells 2"], r_est, est_temp
) -> Float[Array, "nodes 2"]:
    """Eq. (13) on the tempered posterior `p^(1 / est_temp)` (est_temp = 1: eq. 13 itself) [m].

    A grid posterior after many epochs sits in one cell, so eq. (13) is piecewise constant in the
    parameters (zero gradient); tempering spreads the window weights over the neighbouring cells by
    their log-posterior differences, a sub-cell estimate that moves smoothly with the parameters.
    The `truth` objective uses a window of at least 1.5 cells (the 3 x 3 cells around the MLE).
    """
    lp = logpost.reshape(logpost.shape[0], -1)
    return jax.vmap(G.window_estimate, in_axes=(0, None, None))(lp / est_temp, cells, r_est)


def _bfgs(theta0, prob: Problem | tuple[Problem, ...], rtol: float, atol: float, max_steps: int, on_step=None):
    """Optimistix BFGS stepped from Python (one objective evaluation per step, its gradient when
    the line search accepts the point), so that a caller can show progress.

    The values come from the solver's own evaluations, not from extra runs of the objective: the
    first step evaluates the start (always accepted), and the state keeps the value of the last
    accepted point, which is what is returned. Stops early when an accepted step after the first
    move (a plain gradient step, whose length is the gradient's) lowers the value by less than
    `rtol` (relative: the surrogate's last digits, far inside what the guard can tell apart), or
    after `PATIENCE` steps in a row that the line search rejects.

    Returns:
        (theta: the last accepted point, steps, converged, message, value at theta0, value at
        theta).
    """
    solver: optx.AbstractMinimiser = optx.BFGS(rtol=rtol, atol=atol)
    f = objective  # looked up per call (a test may replace it); the compiled step is cached per function
    f_struct = jax.ShapeDtypeStruct((), theta0.dtype)
    state = solver.init(_with_aux(f), theta0, prob, {}, f_struct, f_struct, frozenset())

    def step(y, state, args):
        return _bfgs_step(f, solver, y, state, args)

    def terminate(y, state, args):
        return _bfgs_terminate(f, solver, y, state, args)

    theta, steps = theta0, 0
    first = best = math.nan
    rejected, small = 0, False
    done, result = terminate(theta, state, prob)
    # the first step evaluates the start and does not move: it runs even with max_steps = 0
    while not bool(done) and steps < max(max_steps, 1) and rejected < PATIENCE and not small:
        n_acc = int(state.num_accepted_steps)
        theta, state, _ = step(theta, state, prob)
        steps += 1
        v = float(state.f_info.f)  # the objective at theta, the last accepted point
        if steps == 1:
            first = best = v
            if not math.isfinite(v):
                break
        elif int(state.num_accepted_steps) > n_acc:
            # the first move is the gradient itself (identity Hessian): its size says nothing
            # about what is left to gain, so the small-gain stop applies from the second move on
            small = int(state.num_accepted_steps) > 2 and v > best - rtol * abs(best)
            best, rejected = min(best, v), 0
        else:
            rejected += 1
        if on_step is not None:
            on_step(steps, v)
        done, result = terminate(theta, state, prob)
    ok = bool(done) and result == optx.RESULTS.successful
    if ok:
        message = "converged"
    elif bool(done):
        message = str(cast(Any, optx.RESULTS)[result]).split(".")[0]
    elif small:
        message = f"last step gained < {rtol:g} (relative)"
    elif rejected >= PATIENCE:
        message = f"no progress in {PATIENCE} steps"
    else:
        message = f"stopped at {max_steps} steps"
    return theta, steps, ok, message, first, float(state.f_info.f)


PATIENCE = 4  # line-search rejections in a row before `_bfgs` stops


def _with_aux(f):
    """`f(theta, args)` as Optimistix's (value, aux) function."""

    def fn(theta, args):
        v = f(theta, args)
        return v, v

    return fn


# Module-level programs (the objective and the solver are static arguments): a later `tune` on problems of
# the same shapes, in the same process, reuses the compiled BFGS step (a notebook re-running a cell,
# `tune` on several configurations) instead of tracing and compiling it again.
@eqx.filter_jit
def _bfgs_step(f, solver, y, state, args):
    return solver.step(_with_aux(f), y, args, {}, state, frozenset())


@eqx.filter_jit
def _bfgs_terminate(f, solver, y, state, args):
    return solver.terminate(_with_aux(f), y, args, {}, state, frozenset())


@dataclasses.dataclass(frozen=True)
class TuneResult:
    """Outcome of `tune`.

    Attributes:
        params: the values to use {sigma_r [m], sigma_v [m per epoch], tau} (plus nlos_weight,
            nlos_mean_m [m] with the mixture range model): the tuned ones when `accepted`, else the
            start.
        start: the start values; tuned: what the optimiser ended at (same keys).
        objective: one of `OBJECTIVES` (as asked; `settings["objective_used"]` says
            when evidence fell back to nlpl).
        before, after: the gradient objective (soft cut, on the tuning data) at start and end.
        hard_before, hard_after: `check` of the start and of the tuned values: the filter exactly
            as `calibrate` runs it (hard cut, its cell size and likelihood path, the whole dataset)
            {rmse_m, final_rmse_m, availability, nlpl; heldout_m, consensus_m where computed}. When the held-out guard
            keeps the start, `hard_after` is {heldout_m} alone (the plain run of values that are
            not written is skipped).
        accepted: whether the tuned values are better than the start under the guard's figure
            (`hard_key`: `rmse_m` for truth, the held-out range error for evidence, `consensus_m`
            for consensus).
        steps: BFGS steps. converged: whether BFGS met its tolerance. message: how it ended.
        settings: {epochs, cell_m, check_cell_m, n_cells_side, segment, tau_temp, dtype, ...}.
        seconds: {tune, check}: wall time of the gradient phase and of the two hard runs.
    """

    params: dict
    start: dict
    tuned: dict
    objective: str
    before: float
    after: float
    hard_before: dict
    hard_after: dict
    accepted: bool
    steps: int
    converged: bool
    message: str
    settings: dict
    seconds: dict

    @property
    def hard_key(self) -> str:
        """The hard figure the guard compared (`hard_key` of the objective used)."""
        return hard_key(self.settings.get("objective_used", self.objective), self.hard_before)


_LIKE = "a set needs one objective (metres and nats do not average); tune recordings of >= 5 nodes together"


def _tail_states(dataset, params, objective_name, config, split):
    """The start's filter states before epoch `split` (calibrate's run, hard cut, its precision):
    one per fold for evidence (and that run's held-out pair errors), else one (and None)."""
    if objective_name == "evidence" and tune_eval.pair_folds(dataset.n_nodes):
        return tune_eval.heldout_split(dataset, params, config, split)
    cfg, prm, inp, lp0, _ = pgp.prepare(dataset, params, config, "pgp")
    st, _ = tune_eval.advance(cfg, prm, inp, pgp.init_state(cfg, lp0), 0, split)
    return None, [st]


def tune(
    dataset: MeshDataset | Sequence[MeshDataset],
    params: pgp.PGPParams | dict | None = None,
    config: str | None = None,
    *,
    objective_name: str = "evidence",
    epochs: int | None = None,
    cell_m: float | None = None,
    tau_temp: float = 0.05,
    max_steps: int = 12,
    rtol: float = 1e-3,
    atol: float = 1e-4,
    segment: int | None = None,
    tail: int | None = None,
    progress: ProgressCallback | None = None,
    on_step: Callable[[int, float], None] | None = None,
    on_phase: Callable[[str], None] | None = None,
) -> TuneResult:
    """Fit sigma_r, sigma_v and tau (and with `range_model="mixture"` nlos_weight and
    nlos_mean_m) of the PGP filter by BFGS; keep them only if `calibrate` does better with them.

    Gradient phase: BFGS on the objective with the soft cut of tau, over the first `epochs` epochs
    (None: all) on a grid of `cell_m` cells (None: `params.cell_m`, calibrate's), the filter's
    likelihood path from `params`, in float64, the scan in checkpointed segments of `segment` epochs
    (`mesh.segmented`: memory ~ 2 sqrt(K) carries). With `tail`, the filter runs every epoch but
    is differentiated through the last `tail` only (truncated back-propagation): the earlier epochs
    are calibrate's own run with the start values (hard cut, its precision, `tune_eval.advance`),
    whose state (per held-out fold) the differentiated epochs start from. The objective reads the
    final estimates, which the last epochs move most; the guard still judges the whole run. For
    evidence with `epochs` and `cell_m` None, those prefix runs are also the guard's start runs.
    Guard: `tune_eval.hard_metrics` of the start
    and of the end on the whole dataset with `params` as `calibrate` will run them; the tuned values
    are returned only if their hard figure (`hard_key`: `rmse_m` for truth, for evidence the
    cross-validated range error of held-out pairs, `tune_eval.heldout_range_error`) is lower.

    A set of recordings (a sequence of datasets, the same `params` and `config` for each): the
    objective is the mean of the recordings' objectives (each recording counts once, whatever its
    node count), and the guard pools them: the mean of their hard figures must fall, the paired t
    of the pooled units (every recording's held-out pairs or nodes) must exceed `GUARD_T`, and no
    recording may get clearly worse on its own (its own t < -`GUARD_T`:
    `settings["worse_recording"]` names it). One recording is exactly the one-recording tune.

    Args:
        dataset: a mesh dataset (ground truth needed for `objective_name="truth"`), or a sequence
            of them (a set: the objective and guard above).
        params: `calibrate`'s parameters (`PGPParams` or overrides): the start point and the
            settings the guard checks with.
        config: frame configuration name.
        objective_name: one of `OBJECTIVES` (module docstring; "truth" needs the ground truth).
        epochs, cell_m: a cheaper surrogate for the gradient phase (None: what calibrate runs).
        tail: differentiate the last `tail` epochs only (None or >= the epochs: all of them).
        tau_temp: temperature of the soft tau cut. max_steps, rtol, atol: BFGS settings.
        segment: epochs per checkpointed segment (None: `segmented.segment_length(K)`, about sqrt(K)).
        progress: called with 1 after every BFGS step. on_step: called with (step, objective at
            the last accepted point). on_phase: called with a short text when the guard starts
            a run (calibrate's runs of the start, then of the tuned values; with a set, naming
            the recording).

    Returns:
        A `TuneResult`; `params` go into `jaxcal calibrate --params`. With a set, `hard_before` and
        `hard_after` are the recordings' means and `settings["recordings"]` has each one's figures.
    """
    import time

    if objective_name not in OBJECTIVES:
        raise JaxcalError(f"objective: one of {', '.join(OBJECTIVES)}; got {objective_name!r}")
    if not isinstance(params, pgp.PGPParams):
        params = with_overrides(pgp.PGPParams(), params)
    sets = [dataset] if isinstance(dataset, MeshDataset) else list(dataset)
    if not sets:
        raise JaxcalError("tune: no recording given")
    for d in sets:
        if d.n_epochs == 0:
            raise JaxcalError(f"{d.name}: no epochs to tune on")
        if pgp.uses_local(d, params, config):  # calibrate runs node-local grids there, tuning the global grid
            raise pgp.global_grid_only("tune", d.name)
    many = len(sets) > 1
    if objective_name == "evidence" and len({bool(tune_eval.pair_folds(d.n_nodes)) for d in sets}) > 1:
        few = next(d.name for d in sets if not tune_eval.pair_folds(d.n_nodes))
        raise JaxcalError(f"{few}: fewer than 5 nodes, no pair to hold out (evidence is nlpl there): {_LIKE}")

    def phase(text: str, i: int = 0) -> None:
        if on_phase is not None:
            on_phase(f"{text} (recording {i + 1}/{len(sets)}: {sets[i].name})" if many else text)

    surrogate = params if cell_m is None else dataclasses.replace(params, cell_m=float(cell_m))
    wins = [window(d, epochs) for d in sets]
    mix = params.range_model == "mixture"
    t0 = time.perf_counter()
    # the consensus reference: one batch fit of each whole recording, for the gradient phase and guard
    asked, fallback = objective_name, ""
    refs: list = [None] * len(sets)
    if objective_name == "consensus":
        try:
            for i, d in enumerate(sets):
                if many:
                    phase("consensus: the batch fit", i)
                refs[i] = tune_eval.consensus_reference(d, config)
        except JaxcalError as e:  # no reference: the held-out objective, which needs none either
            objective_name, fallback, refs = "evidence", str(e), [None] * len(sets)
    splits = [max(0, w.n_epochs - int(tail)) if tail else 0 for w in wins]
    pairs_before: list = [None] * len(sets)
    states: list = [None] * len(sets)
    for i, (d, w, split) in enumerate(zip(sets, wins, splits, strict=True)):
        if split:
            if many:
                phase("calibrate's run up to the differentiated epochs", i)
            pairs, states[i] = _tail_states(w, surrogate, objective_name, config, split)
            if w is d and cell_m is None:  # calibrate's own run of the start: the guard's too
                pairs_before[i] = pairs
    with jax.enable_x64(True):  # gradients through thousands of log-posterior epochs need float64
        probs = [
            make_problem(
                w,
                surrogate,
                config,
                objective_name,
                tau_temp,
                segment=segment,
                tail_from=split,
                states=st,
                reference=ref,
            )[0]
            for w, split, st, ref in zip(wins, splits, states, refs, strict=True)
        ]
        kinds = {p.kind for p in probs}
        if len(kinds) > 1:  # evidence on < 5 nodes is nlpl: a mean of both would mix metres and nats
            small = [d.name for d, p in zip(sets, probs, strict=True) if p.kind != probs[0].kind]
            raise JaxcalError(f"{small[0]}: the objective would be {sorted(kinds)} across the recordings: {_LIKE}")
        prob = probs[0]
        dtype = prob.logpost0.dtype
        theta0 = theta_of(
            params.sigma_r,
            params.sigma_v,
            params.tau,
            dtype,
            nlos_weight=params.nlos_weight if mix else None,
            nlos_mean_m=params.nlos_mean_m,
        )

        def step_cb(k, v):
            if progress is not None:
                progress(1)
            if on_step is not None:
                on_step(k, v)

        args = tuple(probs) if many else prob
        theta, steps, ok, message, before, after = _bfgs(theta0, args, rtol, atol, max_steps, step_cb)
        if not math.isfinite(before):
            names = ", ".join(d.name for d in sets)
            raise JaxcalError(f"{names}: the objective is undefined at the start (no node localised?)")
        if not math.isfinite(after) or after > before:  # the optimiser's end is never worse
            theta, after = theta0, before
    t1 = time.perf_counter()
    start, tuned = values_of(theta0), values_of(theta)
    g = guard_set(
        sets, params, config, objective_name, with_overrides(params, tuned), tuned == start, refs, pairs_before, phase
    )
    n_ep = sum(w.n_epochs for w in wins)
    return TuneResult(
        params=tuned if g["accepted"] else start,
        start=start,
        tuned=tuned,
        objective=asked,
        before=before,
        after=after,
        hard_before=g["hard_before"],
        hard_after=g["hard_after"],
        accepted=g["accepted"],
        steps=steps,
        converged=ok,
        message=message,
        settings={
            "epochs": n_ep,  # with a set: over all recordings (each one's in `recordings`)
            "grad_from": sum(splits),  # epochs before it: calibrate's run, not differentiated
            "cell_m": surrogate.cell_m,
            "check_cell_m": params.cell_m,
            "check_epochs": sum(d.n_epochs for d in sets),
            "likelihood": params.likelihood,
            "objective_used": prob.kind,
            "n_cells_side": prob.cfg.grid.n_side,
            "segment": prob.segment or segment_length(wins[0].n_epochs - splits[0]),
            "tau_temp": tau_temp,
            "dtype": str(dtype),
            "rtol": rtol,
            "atol": atol,
            "max_steps": max_steps,
            "guard_gain_t": g["t"],  # t of the per-pair (evidence) or per-node (consensus) gain; NaN: not used
            "guard_t_min": GUARD_T,
            # consensus: nodes the batch fit left unplaced (not scored; -1: not used)
            "consensus_unplaced": -1 if refs[0] is None else sum(int((~np.isfinite(r).all(-1)).sum()) for r in refs),
            "fallback_reason": fallback,  # why consensus fell back to evidence ("" when it did not)
            "recordings": g["recordings"],  # per recording: name, epochs, hard figures, own t
            "worse_recording": g["worse"],  # a set: the recording that got clearly worse ("" none)
        },
        seconds={"tune": t1 - t0, "check": time.perf_counter() - t1},
    )
