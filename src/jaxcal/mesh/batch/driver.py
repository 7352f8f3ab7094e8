"""The `--method batch` driver: `solve` runs the stages (multi-start fit, relocation, offset choice,
all-ranges refinement, covariance, posterior sampler, pair-level covariance) on a range stream, and
`calibrate` wraps it for a `MeshDataset`. The model and the stages' numerics live in the sibling modules."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from jaxcal import solver as S
from jaxcal.data import MeshDataset, Result
from jaxcal.mesh.batch.bootstrap import offset_bootstrap
from jaxcal.mesh.batch.covariance import (
    _covariance,
    _covariance_nodes,
    _pair_level_covariance,
    _restrict,
    covariance_union,
    posterior_excess,
)
from jaxcal.mesh.batch.fit import (
    _extra_starts,
    _fit_starts,
    _initial_starts,
    _irls_all,
    _pair_locations,
    _relocation_candidates,
)
from jaxcal.mesh.batch.model import _Numbers, _State
from jaxcal.mesh.batch.params import RHAT_MAX, BatchParams, BatchSolution, Observations, observations
from jaxcal.mesh.batch.problem import _bucket, _pad, _pair_matrix, _prepare, _Problem
from jaxcal.mesh.batch.sampler import posterior_defect, posterior_mean
from jaxcal.mesh.frame import to_frame
from jaxcal.mesh.relocation import neighbour_table
from jaxcal.params import as_dict, with_overrides
from jaxcal.precision import in_float64


@dataclasses.dataclass(frozen=True)
class _Fit:
    """The fit the answer rests on, as the stages refine it.

    Attributes:
        state: positions (m, D) and offsets, in the fit's own frame.
        cost: robust cost on the median summary after the multi-start fit and relocation.
        code: outcome code (`jaxcal.solver.outcome`) of the last fit that gave `state`.
    """

    state: _State
    cost: float
    code: Array


@dataclasses.dataclass(frozen=True)
class _Refit:
    """Refines a batch of starts (`_fit_starts`) with the settings of `solve`: one batch size for the
    multi-start fit, relocation and offset refit, so that one compilation serves them all."""

    params: BatchParams
    size: int  # batch size (the number of starts of the multi-start fit)
    tail: int  # per-node offsets that enter no range: solved apart (`fit._solver`)

    def graduation(self) -> Array:
        """Loss-scale factors of the multi-start fit's graduated non-convexity stages."""
        return jnp.asarray(2.0 ** np.arange(self.params.gnc_stages - 1, -1, -1), dtype=float)

    def __call__(self, starts: _State, obs: Observations, numbers: _Numbers, graduated: bool = False):
        """(final states, costs (inf where not finite), outcome codes) of every start; without `graduated`
        the multi-start fit's stages and tolerances run at the narrow loss (all but the last stop at gnc_tol)."""
        p, factors = self.params, self.graduation()
        if not graduated:
            factors = jnp.ones_like(factors)
        states, costs, codes = _fit_starts(
            starts, obs, numbers, p.solver, p.tol, p.max_steps, factors, p.gnc_tol, self.tail
        )
        costs = np.where(np.isfinite(np.asarray(costs)), np.asarray(costs), np.inf)
        return states, costs, codes


@dataclasses.dataclass
class _Estimate:
    """The reported estimate in the anchor frame: the fit's, or the posterior mean's (`estimate=mean`).

    Attributes:
        frame: (m, D) positions of the active nodes in the anchor frame.
        mask: (m, D) bool, the free (not gauge-fixed) coordinates.
        offset: common range offset c [m]; node_offsets: (m,) per-node offsets [m].
        model_covariance: (F, F) the model's own covariance of the free coordinates.
        used: `map` or `mean`; reason: why `estimate=mean` fell back to the fit ("" when it did not).
        accept, rhat, transitions: the sampler's acceptance rate, largest split R-hat, transitions per chain.
        excess: (F, F) the posterior's excess over its linearisation (`posterior_excess`; with `used=mean`).
        keep: (m,) the nodes the covariance rests on (`_covariance_nodes`); `mask` is False for the others.
    """

    frame: np.ndarray
    mask: np.ndarray
    offset: float
    node_offsets: np.ndarray
    model_covariance: np.ndarray
    used: str = "map"
    reason: str = ""
    accept: float = float("nan")
    rhat: float = float("nan")
    transitions: int = 0
    excess: np.ndarray | None = None
    keep: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=bool))


def stage_count(params: BatchParams) -> int:
    """Stages `solve` reports to its `progress` callback: multi-start fit, relocation, offset choice
    (bias=auto), all-ranges refinement (summary=all), covariance, posterior sampler (estimate=mean)."""
    p = params
    return 3 + (p.bias == "auto") + (p.summary == "all") + (p.estimate == "mean")


def _multi_start_fit(
    prob: _Problem, p: BatchParams, nb: _Numbers, key: Array, extra_starts: np.ndarray | None
) -> tuple[_Fit, np.ndarray, _Refit]:
    """Stage 1: every start refined with a graduated loss; the lowest robust cost wins. Returns the fit, the
    cost reached from every start and the refitter that the later stages reuse."""
    w_pair = np.isfinite(prob.distances).astype(float)
    # a fixed number of starts whatever N: relocation (`_relocate`) repairs the nodes that no start placed well
    x0s = _initial_starts(
        jnp.asarray(np.nan_to_num(prob.distances)),
        jnp.asarray(w_pair),
        key,
        p.dim,
        p.init,
        p.n_starts,
        p.smacof_iters,
    )
    if extra_starts is not None:
        x0s = jnp.concatenate([x0s, jnp.asarray(_extra_starts(extra_starts, prob.sub, np.asarray(x0s[0]), p.dim))])
    s_count, m = x0s.shape[0], prob.m
    refit = _Refit(p, s_count, 0 if p.bias == "node" else m)
    y0s = _State(x0s, jnp.zeros(s_count), jnp.zeros((s_count, m)))
    states, costs, fit_codes = refit(y0s, prob.pairs, nb, graduated=True)
    best = int(np.argmin(costs))
    state, code = jax.tree.map(lambda a: a[best], states), fit_codes[best]  # code: of the fit `state` is
    return _Fit(state, float(costs[best]), code), costs, refit


def _relocate(prob: _Problem, p: BatchParams, nb: _Numbers, refit: _Refit, fit: _Fit) -> _Fit:
    """Stage 2: rounds of single-node relocation (`BatchParams.relocate_rounds`), each kept if the cost drops."""
    grid_n = p.relocate_grid if p.dim == 2 else max(p.relocate_grid // 3, 2)
    table = neighbour_table(prob.distances, _pair_matrix(prob.pairs, prob.m))
    for _ in range(p.relocate_rounds):
        starts = _relocation_candidates(fit.state, table, nb, grid_n, p.relocate_candidates)
        if starts.x.shape[0] < refit.size:  # same batch size as the multi-start fit: one compilation serves both
            starts = jax.tree.map(lambda a: jnp.concatenate([a, a[:1].repeat(refit.size - a.shape[0], axis=0)]), starts)
        moved, moved_costs, moved_codes = refit(starts, prob.pairs, nb)
        k = int(np.argmin(moved_costs))
        if not moved_costs[k] < fit.cost - 1e-9 * max(1.0, abs(fit.cost)):
            break
        fit = _Fit(jax.tree.map(lambda a, k=k: a[k], moved), float(moved_costs[k]), moved_codes[k])
    return fit


def _choose_offset(
    prob: _Problem, p: BatchParams, nb: _Numbers, key: Array, refit: _Refit, fit: _Fit
) -> tuple[str, np.ndarray, np.ndarray, _Numbers, _Fit]:
    """Stage 3 (`bias=auto`): keep the network offset or refit without it, whichever the residual bootstrap
    predicts to place the nodes better. Returns the offset model used, the bootstrap RMSEs and outcome codes,
    and the numbers and fit of that model."""
    boot, boot_codes = (
        np.asarray(a)
        for a in offset_bootstrap(
            fit.state, prob.pairs, nb, jax.random.fold_in(key, 7), p.n_boot, p.solver, p.tol, p.max_steps, refit.tail
        )
    )
    if not boot[1] < boot[0]:
        return "network", boot, boot_codes, nb, fit
    # leaving the offset out is predicted to place the nodes better
    nb = eqx.tree_at(lambda t: t.use_c, nb, jnp.zeros_like(nb.use_c))
    start = eqx.tree_at(lambda t: t.c, fit.state, jnp.zeros_like(fit.state.c))
    starts = jax.tree.map(lambda a: jnp.repeat(a[None], refit.size, axis=0), start)
    states, _, codes = refit(starts, prob.pairs, nb)
    return (
        "none",
        boot,
        boot_codes,
        nb,
        dataclasses.replace(fit, state=jax.tree.map(lambda a: a[0], states), code=codes[0]),
    )


def _refine_all_ranges(
    prob: _Problem, p: BatchParams, nb: _Numbers, refit: _Refit, fit: _Fit
) -> tuple[Observations, Observations, _Fit]:
    """Stage 4 (`summary=all`): IRLS over every single range. Returns all ranges as observations, the pair
    observations of the posterior (where the all-ranges fit puts them, with `estimate=mean`) and the fit."""
    m, pw = prob.m, prob.pair_weights
    i_a, j_a, z_a, w_a = observations(prob.ranges, "all")
    obs = prob.observations(i_a, j_a, z_a, w_a if pw is None else pw[i_a, j_a])
    oi, oj = np.asarray(obs.i), np.asarray(obs.j)
    key_pair = np.minimum(oi, oj) * m + np.maximum(oi, oj)  # padding maps to pair (0, 0), weight 0
    uniq, pair_of_obs = np.unique(key_pair, return_inverse=True)
    size = _bucket(uniq.size)
    pair_i, pair_j = jnp.asarray(_pad(uniq // m, size)), jnp.asarray(_pad(uniq % m, size))
    state, code = _irls_all(
        fit.state,
        obs,
        pair_i,
        pair_j,
        jnp.asarray(pair_of_obs),
        nb,
        p.solver,
        p.tol,
        p.max_steps,
        p.irls_iters,
        refit.tail,
    )
    obs_pairs = prob.pairs
    if p.estimate == "mean":  # the posterior's pair observations: where the all-ranges fit puts them
        obs_pairs = _pair_locations(state, obs, pair_i, pair_j, jnp.asarray(pair_of_obs), nb)
    jax.block_until_ready(state.x)
    return obs, obs_pairs, dataclasses.replace(fit, state=state, code=code)


def _anchor_frame(prob: _Problem, p: BatchParams, state: _State) -> tuple[np.ndarray, np.ndarray]:
    """The fitted positions (m, D) in the anchor frame (3-D: the mirror image `z_up` picks) and the mask of
    the free coordinates (a0 fixed; a1 only x; in 3-D a2 has no z); fixed coordinates are set to 0."""
    a0, a1, a2 = (int(prob.remap[a]) for a in prob.anchors)
    x_frame_sub = to_frame(np.asarray(state.x), a0, a1, a2)
    if p.dim == 3:
        # Ranges cannot tell a 3-D scene from its mirror image through the a0-a1-a2 plane; pick the
        # one where the other nodes lie mostly above it (z up), or below with z_up=false.
        others = np.ones(prob.m, dtype=bool)
        others[[a0, a1, a2]] = False
        zsum = float(np.sum(x_frame_sub[others, 2]))
        if (zsum < 0) == p.z_up:
            x_frame_sub[:, 2] *= -1.0
    mask = np.ones((prob.m, p.dim), dtype=bool)
    mask[a0, :] = False
    mask[a1, 1:] = False
    if p.dim == 3:
        mask[a2, 2] = False
    x_frame_sub[~mask] = 0.0
    return x_frame_sub, mask


def _sample_posterior(
    prob: _Problem,
    p: BatchParams,
    nb: _Numbers,
    key: Array,
    chosen: str,
    state: _State,
    pairs: Observations,
    est: _Estimate,
    done: Callable[[int], None],
) -> _Estimate:
    """Stage 6 (`estimate=mean`): the posterior mean and covariance (`posterior_mean`) replace the fit in
    `est`, unless the graph makes the posterior improper (`posterior_defect`) or the chains do not mix."""
    n_off = int(chosen != "none")  # per-node offsets have a proper prior of their own
    # the graph of the nodes the covariance rests on (`_covariance_nodes`): the others are not sampled
    kept = np.flatnonzero(est.keep)
    ids = tuple(prob.node_ids[k] for k in prob.sub[kept])
    index = np.full(prob.m, -1)
    index[kept] = np.arange(kept.size)
    both = est.keep[prob.pair_i] & est.keep[prob.pair_j]
    pi, pj = index[prob.pair_i[both]], index[prob.pair_j[both]]
    est.reason = posterior_defect(pi, pj, kept.size, p.dim, p.student_nu, n_off, ids, p.seed)
    if est.reason:
        return est
    free = est.frame[est.mask]
    mean, cov_s, acc, rh, n_run, lap_s = posterior_mean(
        jnp.asarray(free),
        jnp.asarray(est.frame),
        jnp.asarray(est.mask),
        state.c,
        state.b,
        pairs,
        nb,
        jax.random.fold_in(key, 11),
        jnp.asarray(float(p.student_nu)),
        p.mcmc_chains,
        p.mcmc_steps,
        chosen == "node",
        float(p.mcmc_mcse),
        p.sampler,
    )
    f = free.size
    mean, cov_s = np.asarray(mean), np.asarray(cov_s)
    est.accept, est.rhat, est.transitions = float(acc), float(rh), int(n_run)
    done(1)
    if est.rhat <= RHAT_MAX and np.isfinite(mean).all() and np.isfinite(cov_s).all():
        est.frame[est.mask] = mean[:f]
        est.model_covariance, est.offset, est.node_offsets = cov_s[:f, :f], float(mean[f]), mean[f + 1 :]
        est.excess = posterior_excess(est.model_covariance, np.asarray(lap_s)[:f, :f], float(p.student_nu))
        est.used = "mean"
    else:
        est.reason = f"the posterior chains did not mix (split R-hat {est.rhat:.2f}, limit {RHAT_MAX:.2f})"
    return est


def _per_node(prob: _Problem, mask: np.ndarray, cov_f: np.ndarray, defined: np.ndarray) -> np.ndarray:
    """(F, F) covariance over the free coordinates -> (N, D, D) per-node blocks, NaN where undefined (and
    for the active nodes not in `defined` (m,))."""
    m, dim = mask.shape
    full_idx = np.flatnonzero(mask.ravel())
    cov_all = np.zeros((m * dim, m * dim))
    cov_all[np.ix_(full_idx, full_idx)] = cov_f
    blocks = np.stack([cov_all[k * dim : (k + 1) * dim, k * dim : (k + 1) * dim] for k in range(m)])
    blocks = 0.5 * (blocks + np.swapaxes(blocks, 1, 2))
    blocks[~np.isfinite(blocks).all(axis=(1, 2)) | ~defined] = np.nan
    out = np.full((prob.n, dim, dim), np.nan)
    out[prob.sub] = blocks
    return out


@in_float64
def solve(
    range_m: np.ndarray,
    anchors: tuple[int, int, int],
    params: BatchParams | None = None,
    node_ids: tuple[str, ...] | None = None,
    extra_starts: np.ndarray | None = None,
    progress: Callable[[int], None] | None = None,
) -> BatchSolution:
    """Robust batch fit of static node positions from a range stream.

    Args:
        range_m: (K, N, N) ranges [m], NaN = missing.
        anchors: (a0, a1, a2) node indices that define the output frame.
        params: `BatchParams` (defaults when None).
        node_ids: optional ids, only used in error messages.
        extra_starts: optional (E, N, D) start configurations (e.g. PGP posterior modes), any frame, D <= dim;
            NaN rows are filled from classical MDS. Each is added with its mirror image to the MDS / SMACOF
            starts, so the best robust cost can only go down.
        progress: called with 1 after each stage (`stage_count(params)` calls in all).

    Returns:
        A `BatchSolution` in the anchor frame.

    Raises:
        JaxcalError: when a0, a1 or a2 are not connected by ranges, or fewer than dim + 1 nodes are.
    """
    p = params or BatchParams()
    done = progress or (lambda k: None)  # one call per finished stage (`stage_count`)
    prob = _prepare(range_m, anchors, p, node_ids)
    nb = _Numbers.of(p)
    key = jax.random.PRNGKey(p.seed)
    fit, costs, refit = _multi_start_fit(prob, p, nb, key, extra_starts)
    done(1)
    fit = _relocate(prob, p, nb, refit, fit)
    done(1)
    chosen, boot, boot_codes = ("network" if p.bias == "auto" else p.bias), np.full(2, np.nan), np.zeros(0)
    if p.bias == "auto":
        chosen, boot, boot_codes, nb, fit = _choose_offset(prob, p, nb, key, refit, fit)
        done(1)
    obs = obs_pairs = prob.pairs  # obs_pairs: what the posterior of estimate=mean sees, one per pair
    if p.summary == "all":
        obs, obs_pairs, fit = _refine_all_ranges(prob, p, nb, refit, fit)
        done(1)
    state = fit.state
    x_frame_sub, mask = _anchor_frame(prob, p, state)
    # Only the nodes the measured graph fixes, and the ranges between them, enter the covariance problem
    b0, b1, b2 = (int(prob.remap[a]) for a in prob.anchors)
    ids = tuple(prob.node_ids[k] for k in prob.sub)
    keep = _covariance_nodes(prob.pair_i, prob.pair_j, prob.m, (b0, b1, b2), p.dim, ids)
    mask = mask & keep[:, None]
    obs, obs_pairs, pairs = _restrict(obs, keep), _restrict(obs_pairs, keep), _restrict(prob.pairs, keep)
    free = x_frame_sub[mask]
    cov_free, s2 = _covariance(
        jnp.asarray(free), jnp.asarray(x_frame_sub), jnp.asarray(mask), state.c, state.b, obs, nb
    )
    done(1)
    est = _Estimate(x_frame_sub, mask, float(state.c), np.asarray(state.b), np.asarray(cov_free), keep=keep)
    if p.estimate == "mean":
        est = _sample_posterior(prob, p, nb, key, chosen, state, obs_pairs, est, done)
    # Per-pair systematic errors, sized from the data (`pair_covariance`), at the estimate reported
    cov_pair = _pair_level_covariance(
        prob.ranges,
        prob.sub,
        prob.pair_i,
        prob.pair_j,
        est.frame,
        mask,
        est.offset,
        est.node_offsets,
        pairs,
        obs,
        nb,
    )
    f = free.size
    if est.excess is not None:  # (used=mean) the pair covariance plus what the posterior adds to its linearisation
        cov_free = covariance_union(est.excess, est.excess + cov_pair[:f, :f])
    else:  # the Laplace covariance of the all-ranges fit, widened to the pair covariance
        cov_free = covariance_union(est.model_covariance, cov_pair[:f, :f])
    position = np.full((prob.n, p.dim), np.nan)
    position[prob.sub] = est.frame
    node_off = np.full(prob.n, np.nan)
    node_off[prob.sub] = est.node_offsets if chosen == "node" else 0.0
    return BatchSolution(
        position=position,
        covariance=_per_node(prob, mask, cov_free, keep),
        offset_m=est.offset if chosen != "none" else 0.0,
        node_offset_m=node_off,
        cost=fit.cost,
        start_costs=costs,
        residual_sigma_m=float(np.sqrt(s2)),
        bias=chosen,
        boot_rmse_m=boot,
        mcmc_accept=est.accept,
        mcmc_rhat=est.rhat,
        estimate=est.used,
        fallback_reason=est.reason,
        model_covariance=_per_node(prob, mask, est.model_covariance, keep),
        solver_codes=np.append(np.asarray(fit.code), boot_codes).astype(int),
        mcmc_transitions=est.transitions,
    )


def warn_if_unmixed(solution: BatchSolution, params: BatchParams) -> bool:
    """Log one warning line (logger `jaxcal`) when `estimate=mean` fell back to the fit; True if so."""
    if params.estimate != "mean" or solution.estimate == "mean":
        return False
    hint = "add ranges"
    if "R-hat" in solution.fallback_reason:
        hint = f"raise mcmc_steps (now {params.mcmc_steps}) or add ranges"
    logging.getLogger("jaxcal").warning(
        "batch: %s: reporting the fit (estimate=map) and its covariance instead; %s",
        solution.fallback_reason or "the posterior mean is not available",
        hint,
    )
    return True


def check_solver(solution: BatchSolution, params: BatchParams, method: str = "batch") -> S.SolverReport:
    """The outcome of the fits `solution` rests on (`BatchSolution.solver_codes`), with one warning line (logger
    `jaxcal`) when one of them did not converge; its `params()` go into the Result params."""
    rep = S.report(solution.solver_codes, "fits")
    rep.warn(method, f"raise max_steps (now {params.max_steps}) or tol (now {params.tol:g})")
    return rep


def calibrate(
    dataset: MeshDataset, params=None, config: str | None = None, progress: Callable[[int], None] | None = None
) -> Result:
    """`--method batch`: robust batch calibration of a static mesh (see the module docstring).

    Args:
        dataset: a `MeshDataset`.
        params: overrides of `BatchParams` (strings from `--set` are cast).
        config: frame configuration name (`dataset.config(config)` gives a0, a1, a2).
        progress: called with 1 after each stage (`stage_count(params)` calls in all).

    Returns:
        A `Result` with final positions and covariances in the a0/a1/a2 frame, no track.
    """
    from jaxcal import __version__
    from jaxcal.mesh import masking

    p = with_overrides(BatchParams(), params)
    anchors = dataset.config(config)
    empty = masking.undetermined_frame_result(dataset, anchors, "batch", p.dim, as_dict(p))
    if empty is not None:  # the ranges do not fix the frame: nothing to fit (one warning line)
        return empty
    sol = solve(dataset.range, anchors, p, dataset.node_ids, progress=progress)
    warn_if_unmixed(sol, p)
    outcome = check_solver(sol, p)
    p = eqx.tree_at(lambda q: (q.bias, q.estimate), p, (sol.bias, sol.estimate))  # record what was used
    res = Result(
        ids=dataset.node_ids,
        position=sol.position,
        method="batch",
        dataset=dataset.name,
        frame="anchors:" + ",".join(str(a) for a in anchors),
        params={
            **as_dict(p),
            **outcome.params(),
            **({"mcmc_transitions": sol.mcmc_transitions} if sol.mcmc_transitions else {}),
        },
        covariance=sol.covariance,
        software=f"jaxcal {__version__}",
    )
    # nodes the measured graph cannot fix (one neighbour, a flexible part) become NaN rows + a warning
    return masking.mask_result(res, dataset.range)
