"""Robust batch calibration of a static mesh: all epochs at once, robust loss, range bias, covariance.

Model: the measured range of pair (i, j) is `z_ij = ||p_i - p_j|| + c + b_i + b_j + e_ij`, with a common
range offset `c` (`bias="network"`; DWM1001 ranges are typically 0.1-0.3 m short, so `c < 0`), optional
per-node offsets `b_i` (`bias="node"`, antenna delays, with a Gaussian prior of width
`node_bias_sigma_m`) and an error `e` scored by a robust loss rho (Huber, Cauchy, or the negative log of
a LOS / NLOS / outlier mixture). The fit minimises `sum rho(e)` with Optimistix least squares
(Levenberg-Marquardt or Gauss-Newton) on "square-root" residuals `sign(e) sqrt(2 rho(e))`, whose
Gauss-Newton gradient equals the gradient of the robust cost.

`bias="auto"` fits the network offset and then keeps it only if a residual bootstrap predicts a smaller
position error with it than without (`offset_bootstrap`): in weak geometries (nearly planar 3-D scenes) the
offset trades off against the poorly determined directions, and its estimate can cost more than it removes.

Observations are either one robust summary per pair (`summary="median"`: the median over epochs of
each direction, then the mean of the two directions) or every single range (`summary="all"`).

A local fit needs a global start: classical MDS of the distance matrix completed by shortest paths,
SMACOF from it, and SMACOF from several random starts are all refined (vmapped) and the one with the
lowest robust cost wins. A global mirror image has the same cost (it is the gauge, fixed at the end by
`to_frame`); partial flips of weakly connected nodes are what the random starts are for.

Reported estimate (`estimate`): by default the posterior *mean* of the positions (`posterior_mean`), not
the fit itself (the posterior mode, `estimate=map`). In a weak geometry the two differ and the mean is the
one with the least expected squared error. It is sampled from a model where the pair, not the single
range, is the unit of information (repeated ranges of one pair share its systematic error).

Output frame: a0 at the origin, a1 on +x, a2 with y > 0 (CONTRACT 1.1). Covariances are computed in
gauge-fixed coordinates of that frame, so they are exactly zero for the coordinates the frame fixes. The
reported covariance rests on the covariance under per-pair systematic errors whose size is estimated
from the pair residuals (`jaxcal.mesh.pair_covariance`: every pair counted once whatever the number of
epochs, with the part of its error that the geometry absorbs accounted for): with `estimate=map` it
widens the Laplace covariance `sigma^2 (J^T W J)^-1` of the all-ranges fit (W = IRLS weights psi(e)/e)
in every direction (`covariance_union`); with `estimate=mean` the posterior's excess over its own
linearisation is added to it (`posterior_excess`: the width of a curved, weakly determined posterior,
which a linearised covariance cannot see; ~0 where the ranges fix the nodes to first order).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, Int

from jaxcal import solver as S
from jaxcal.data import MeshDataset, Result
from jaxcal.errors import JaxcalError
from jaxcal.mesh import mds
from jaxcal.mesh.frame import to_frame
from jaxcal.mesh.pair_covariance import pair_covariance, pair_spread
from jaxcal.mesh.relocation import neighbour_table, relocation_moves
from jaxcal.mesh.sparse_lm import SparseLevenbergMarquardt, normal_equations
from jaxcal.params import as_dict, with_overrides
from jaxcal.precision import in_float64

__all__ = [
    "BatchParams",
    "Observations",
    "BatchSolution",
    "observations",
    "solve",
    "check_solver",
    "calibrate",
    "LOSSES",
]

LOSSES = ("l2", "huber", "cauchy", "mixture")
BIASES = ("auto", "none", "network", "node")
SUMMARIES = ("median", "all")
INITS = ("multi", "cmds", "smacof")
SOLVERS = ("lm", "gn", "lm_dense")
PAIR_WEIGHTS = ("none", "spread")
ESTIMATES = ("map", "mean")
RHAT_MAX = 1.1  # split R-hat above which (or undefined) estimate=mean falls back to the fit (Gelman-Rubin)


class BatchParams(eqx.Module):
    """Parameters of `--method batch` (all settable with `--set KEY=VALUE`).

    Attributes:
        dim: 2 (planar) or 3 (positions in 3-D; a2 fixes the x-y plane).
        loss: robust loss: `l2`, `huber`, `cauchy` (default; redescending, ignores gross outliers),
            `mixture` (LOS Gaussian + exponentially modified Gaussian NLOS + uniform outliers).
        sigma_r: ranging standard deviation / loss scale [m] (LOS width of the mixture).
        bias: range offset model: `none`, `network` (one common offset, default), `node` (common offset
            plus one offset per node), `auto` (`network` or `none`, whichever a residual bootstrap of the
            network fit predicts to give the smaller position error; see `offset_bootstrap`).
        node_bias_sigma_m: prior standard deviation of the per-node offsets [m] (`bias=node`).
        summary: `all` (every range of every epoch, default; fitted by IRLS) or `median` (one robust
            range per pair).
        nlos_weight, nlos_mean_m: mixture share and mean excess length of NLOS ranges.
        outlier_weight, outlier_span_m: mixture share and span [m] of the uniform outlier floor.
        init: `multi` (classical MDS, SMACOF and random SMACOF starts; default), `cmds`, `smacof`.
        n_starts: number of random SMACOF starts (with `init=multi`), whatever N.
        smacof_iters: Guttman transforms per SMACOF run.
        solver: `lm` (Levenberg-Marquardt on the sparse normal equations of the pairs, default; see
            `jaxcal.mesh.sparse_lm`), `gn` (Gauss-Newton) or `lm_dense` (Optimistix's Levenberg-Marquardt
            on the dense Jacobian: the same optimum, at O(M P^2) per step).
        max_steps: iteration limit of the least-squares solver.
        tol: relative and absolute tolerance of the least-squares solver.
        seed: random seed of the random starts (and of the offset bootstrap).
        n_boot: bootstrap replicates of `bias=auto`.
        pair_weight: `none` (every pair counts alike) or `spread` (pairs whose ranges scatter more, over
            epochs and between the two directions, count less; see `spread_weights`).
        gnc_stages: graduated non-convexity: the multi-start fit runs with loss scales
            sigma_r * 2^(G-1), ..., sigma_r (G stages; 1 = no graduation).
        gnc_tol: tolerance of the stages before the last one (`solver=lm`; at most `tol` is never
            tightened): they only carry a start into the basin of the narrow loss, so converging them to
            `tol` spends steps that the last stage repeats (about half of the fit's steps at N = 100).
        relocate_rounds: rounds of single-node relocation after the multi-start fit: every node in
            turn is moved to the best point of a grid over the scene (its own robust cost, the
            others fixed), which undoes flips (mirror images of weakly constrained nodes) and
            placements pulled by a gross outlier; each move is refined and kept if the total cost drops.
            Every move is first refined locally (the node alone, its neighbours fixed: the exact change
            of the total cost, `jaxcal.mesh.relocation`); the `relocate_candidates` moves that lower the
            cost most are refined globally (all of them when N <= relocate_candidates: exhaustive).
        relocate_candidates: moves refitted globally per relocation round (see `relocate_rounds`).
        relocate_grid: grid points per axis of the relocation search (2-D; a third of it per axis in 3-D).
        irls_iters: reweighting rounds of the all-epochs refinement (`summary=all`).
        z_up: 3-D only: of the two mirror images (z -> -z), report the one where the nodes other than
            a0, a1, a2 lie mostly above the a0-a1-a2 plane (true) or below it (false).
        estimate: `mean` (default: posterior mean and sample covariance of the pair-level model, see
            `posterior_mean`; the minimum-mean-square-error estimate, which differs from the fit where
            the geometry is weak) or `map` (the robust fit itself and its Laplace covariance).
        student_nu: degrees of freedom of the Student-t pair likelihood of `estimate=mean` (1 = Cauchy).
        mcmc_chains, mcmc_steps: Hamiltonian Monte Carlo chains and transitions per chain of
            `estimate=mean` (a quarter of it, at most 500, is burn-in; `mcmc_steps` is the most run, see `mcmc_mcse`).
        mcmc_mcse: the sampler stops before `mcmc_steps` once the Monte Carlo error of the posterior mean is
            below this share of the posterior standard deviation in every coordinate and split R-hat is
            below 1.01 (checked every 250 transitions after the burn-in, from the spread of the chains'
            means); 0 runs every step.
    """

    dim: int = 2
    loss: str = "cauchy"
    sigma_r: float = 0.2
    bias: str = "network"
    node_bias_sigma_m: float = 0.1
    n_boot: int = 32
    pair_weight: str = "none"
    summary: str = "all"
    nlos_weight: float = 0.2
    nlos_mean_m: float = 1.0
    outlier_weight: float = 0.05
    outlier_span_m: float = 50.0
    init: str = "multi"
    n_starts: int = 8
    smacof_iters: int = 300
    solver: str = "lm"
    max_steps: int = 200
    tol: float = 1e-9
    seed: int = 0
    z_up: bool = True
    irls_iters: int = 15
    gnc_stages: int = 6
    gnc_tol: float = 1e-4
    relocate_rounds: int = 2
    relocate_grid: int = 48
    relocate_candidates: int = 8
    estimate: str = "mean"
    student_nu: float = 1.0
    mcmc_chains: int = 16
    mcmc_steps: int = 4000
    mcmc_mcse: float = 0.05

    def __check_init__(self):
        for name, allowed in (
            ("loss", LOSSES),
            ("bias", BIASES),
            ("summary", SUMMARIES),
            ("init", INITS),
            ("solver", SOLVERS),
            ("pair_weight", PAIR_WEIGHTS),
            ("estimate", ESTIMATES),
        ):
            if getattr(self, name) not in allowed:
                raise JaxcalError(
                    f"parameter {name}: expected one of {', '.join(allowed)}, got {getattr(self, name)!r}"
                )
        if self.dim not in (2, 3):
            raise JaxcalError(f"parameter dim: expected 2 or 3, got {self.dim}")
        for name in ("sigma_r", "node_bias_sigma_m", "nlos_mean_m", "outlier_span_m", "tol", "gnc_tol", "student_nu"):
            if not getattr(self, name) > 0:
                raise JaxcalError(f"parameter {name}: must be > 0, got {getattr(self, name)}")
        if not self.mcmc_mcse >= 0:
            raise JaxcalError(f"parameter mcmc_mcse: must be >= 0, got {self.mcmc_mcse}")
        for name in ("nlos_weight", "outlier_weight"):
            if not 0 <= getattr(self, name) < 1:
                raise JaxcalError(f"parameter {name}: must be in [0, 1), got {getattr(self, name)}")
        if self.nlos_weight + self.outlier_weight >= 1:
            raise JaxcalError("parameters nlos_weight + outlier_weight must be < 1")
        if (
            min(self.n_starts, self.smacof_iters, self.relocate_rounds) < 0
            or min(
                self.max_steps,
                self.irls_iters,
                self.gnc_stages,
                self.relocate_grid,
                self.n_boot,
                self.mcmc_chains,
                self.relocate_candidates,
            )
            < 1
            or self.mcmc_steps < 8
        ):
            raise JaxcalError(
                "parameters n_starts, smacof_iters, relocate_rounds must be >= 0; "
                "max_steps, irls_iters, gnc_stages, relocate_grid, relocate_candidates, n_boot, "
                "mcmc_chains >= 1; mcmc_steps >= 8"
            )


class Observations(eqx.Module):
    """Ranges as a flat list of observations between the active nodes.

    Attributes:
        i, j: (M,) node indices (into the active nodes).
        z: (M,) measured range [m].
        w: (M,) observation weight (1 per range or per pair summary).
    """

    i: Int[Array, " m"]
    j: Int[Array, " m"]
    z: Float[Array, " m"]
    w: Float[Array, " m"]


class BatchSolution(eqx.Module):
    """What `solve` returns (positions in the anchor frame; all arrays over all N nodes).

    Attributes:
        position: (N, D) [m], NaN for nodes without ranges to the frame's component.
        covariance: (N, D, D) [m^2], NaN where undefined.
        offset_m: fitted common range offset c [m] (0 with `bias=none`).
        node_offset_m: (N,) fitted per-node offsets [m] (0 unless `bias=node`; NaN for inactive nodes).
        cost: robust cost on the median summary after the multi-start fit and relocation (with the
            network offset when `bias=auto`, so that costs of runs with other starts stay comparable).
        start_costs: (S,) robust cost reached from every start.
        residual_sigma_m: weighted residual standard deviation [m].
        bias: the range offset model used (`bias=auto` resolved to `network` or `none`).
        boot_rmse_m: (2,) bootstrap position RMSE [m] of the network-offset and the no-offset fit
            (`bias=auto`; NaN otherwise).
        mcmc_accept, mcmc_rhat: `estimate=mean` only (NaN otherwise): the sampler's acceptance rate and
            the largest split R-hat over the free coordinates.
        estimate: the estimate reported: `mean`, or `map` when asked for, when the measurement graph
            makes the pair-level posterior improper or not locally identifiable (`posterior_defect`,
            decided before any sampling), or when the chains did not mix (R-hat above `RHAT_MAX` or
            undefined).
        fallback_reason: why `estimate=mean` fell back to the fit ("" when it did not).
        model_covariance: (N, D, D) the model's own covariance (posterior sample covariance with
            `estimate=mean`, the Laplace covariance otherwise); the reported covariance is the pair-level
            covariance (`pair_covariance`) widened by the Laplace covariance (`covariance_union`) or by the
            posterior's excess over its linearisation (`posterior_excess`).
        solver_codes: outcome codes (`jaxcal.solver.outcome`) of the fit the answer rests on (the chosen
            start, relocation, offset refit or all-ranges refinement, whichever came last), then of the
            offset bootstrap's replicate fits (`bias=auto`).
        mcmc_transitions: transitions per chain the sampler ran, burn-in included (at most `mcmc_steps`;
            fewer when `mcmc_mcse` was reached first); 0 without sampling.
    """

    position: np.ndarray
    covariance: np.ndarray
    offset_m: float
    node_offset_m: np.ndarray
    cost: float
    start_costs: np.ndarray
    residual_sigma_m: float
    bias: str = "network"
    boot_rmse_m: np.ndarray = eqx.field(default_factory=lambda: np.full(2, np.nan))
    mcmc_accept: float = float("nan")
    mcmc_rhat: float = float("nan")
    estimate: str = "map"
    fallback_reason: str = ""
    model_covariance: np.ndarray | None = None
    solver_codes: np.ndarray = eqx.field(default_factory=lambda: np.zeros(0, dtype=int))
    mcmc_transitions: int = 0


# ---------------------------------------------------------------------------------------------
# Observations (host-side preprocessing, NumPy)


def observations(range_m: np.ndarray, summary: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Flatten a (K, N, N) range stream into observations.

    Args:
        range_m: (K, N, N) ranges [m], NaN = missing.
        summary: `median`: per pair, the nanmedian over epochs of each direction, then the mean of the
            two directions (one observation per unordered pair). `all`: every finite range.

    Returns:
        (i, j, z, w): (M,) int arrays i < j for `median` (any order for `all`), ranges [m], weights.
    """
    r = np.asarray(range_m, dtype=np.float64)
    n = r.shape[1]
    if summary == "median":
        med = np.full((n, n), np.nan)
        ii, jj = np.nonzero(np.isfinite(r).any(axis=0))
        med[ii, jj] = np.nanmedian(r[:, ii, jj], axis=0)  # only columns with a finite value
        iu, ju = np.triu_indices(n, k=1)
        both = np.stack([med[iu, ju], med[ju, iu]])
        cnt = np.isfinite(both).sum(axis=0)
        pair = np.where(cnt > 0, np.nansum(both, axis=0) / np.maximum(cnt, 1), np.nan)
        ok = np.isfinite(pair)
        return iu[ok], ju[ok], pair[ok], np.ones(int(ok.sum()))
    k, ii, jj = np.nonzero(np.isfinite(r))
    ok = ii != jj
    return ii[ok], jj[ok], r[k[ok], ii[ok], jj[ok]], np.ones(int(ok.sum()))


def spread_weights(range_m: np.ndarray) -> np.ndarray:
    """Per-pair weights from the scatter of the pair's own ranges (`pair_weight=spread`).

    On real DWM1001 meshes the pairs whose ranges scatter most (over epochs, and between the i->j and
    j->i directions) are also the ones whose median is furthest from the true distance (multipath), so
    the spread is used as the pair's error scale: w = 1 / (1 + (s / s0)^2), s the standard deviation of
    the pooled ranges of both directions and s0 the median of s over all pairs (no scale to set).

    Args:
        range_m: (K, N, N) ranges [m], NaN = missing.

    Returns:
        (N, N) symmetric weights in (0, 1] (1 where a pair has a single range or s0 is 0).
    """
    r = np.asarray(range_m, dtype=np.float64)
    pooled = np.concatenate([r, np.swapaxes(r, 1, 2)], axis=0)
    cnt = np.isfinite(pooled).sum(axis=0)
    mean = np.nansum(pooled, axis=0) / np.maximum(cnt, 1)
    var = np.nansum((pooled - mean) ** 2, axis=0) / np.maximum(cnt - 1, 1)
    s = np.where(cnt > 1, np.sqrt(var), np.nan)
    off = ~np.eye(r.shape[1], dtype=bool) & np.isfinite(s)
    s0 = float(np.median(s[off])) if off.any() else 0.0
    if not s0 > 0:
        return np.ones(r.shape[1:])
    return np.where(np.isfinite(s), 1.0 / (1.0 + (s / s0) ** 2), 1.0)


# ---------------------------------------------------------------------------------------------
# Losses: rho(e) >= 0 in units of "nats"; sqrt_rho gives a residual f with f^2 / 2 = rho.


class _Numbers(eqx.Module):
    """The numeric and categorical parameters as arrays, so that new values (a new loss included)
    do not recompile: the loss is chosen by an index, the offset model by two 0/1 switches."""

    sigma_r: Array
    node_bias_sigma_m: Array
    nlos_weight: Array
    nlos_mean_m: Array
    outlier_weight: Array
    outlier_span_m: Array
    loss_id: Array
    use_c: Array
    use_b: Array

    @classmethod
    def of(cls, p: BatchParams) -> _Numbers:
        nums = [
            jnp.asarray(float(getattr(p, f)), dtype=float)
            for f in ("sigma_r", "node_bias_sigma_m", "nlos_weight", "nlos_mean_m", "outlier_weight", "outlier_span_m")
        ]
        return cls(
            *nums,
            jnp.asarray(LOSSES.index(p.loss)),
            jnp.asarray(float(p.bias != "none")),
            jnp.asarray(float(p.bias == "node")),
        )

    def with_loss(self, loss: str) -> _Numbers:
        return eqx.tree_at(lambda nb: nb.loss_id, self, jnp.asarray(LOSSES.index(loss)))


def _mixture_logpdf(e, nb: _Numbers):
    """log p(e) of the range error e = z - model [m]: LOS Gaussian, NLOS exponentially modified
    Gaussian (Gaussian convolved with a positive exponential of mean nlos_mean_m), uniform outliers."""
    s, lam = nb.sigma_r, 1.0 / nb.nlos_mean_m
    w_out, w_nlos = nb.outlier_weight, nb.nlos_weight
    w_los = 1.0 - w_nlos - w_out
    log_los = jnp.log(w_los) - 0.5 * (e / s) ** 2 - jnp.log(s * jnp.sqrt(2 * jnp.pi))
    log_nlos = (
        jnp.log(jnp.maximum(w_nlos, 1e-300))
        + jnp.log(lam)
        + 0.5 * (lam * s) ** 2
        - lam * e
        + jax.scipy.special.log_ndtr(e / s - lam * s)
    )
    log_out = jnp.broadcast_to(jnp.log(jnp.maximum(w_out, 1e-300)) - jnp.log(nb.outlier_span_m), e.shape)
    return jax.scipy.special.logsumexp(jnp.stack([log_los, log_nlos, log_out]), axis=0)


def _mixture_logpdf_bound(nb: _Numbers):
    """An upper bound of the mixture density's log (each component's density is bounded)."""
    s, lam = nb.sigma_r, 1.0 / nb.nlos_mean_m
    g = 1.0 / (s * jnp.sqrt(2 * jnp.pi))
    bound = (
        (1.0 - nb.nlos_weight - nb.outlier_weight) * g
        + nb.nlos_weight * jnp.minimum(lam, g)
        + nb.outlier_weight / nb.outlier_span_m
    )
    return jnp.log(bound) + 1e-3  # strictly above: sqrt(rho) stays smooth


def _select(loss_id, branches):
    """branches[loss_id], elementwise; every branch is finite (and has finite gradients) everywhere."""
    out = branches[0]
    for k, b in enumerate(branches[1:], start=1):
        out = jnp.where(loss_id == k, b, out)
    return out


def _rho(e, nb: _Numbers):
    """Robust cost of range errors e [m] (elementwise), for the loss `LOSSES[nb.loss_id]`."""
    u = e / nb.sigma_r
    a = jnp.abs(u)
    l2 = 0.5 * u * u
    huber = jnp.where(a <= 1.0, l2, a - 0.5)
    cauchy = 0.5 * jnp.log1p(u * u)
    mixture = _mixture_logpdf_bound(nb) - _mixture_logpdf(e, nb)
    return _select(nb.loss_id, (l2, huber, cauchy, mixture))


def _sqrt_rho(e, nb: _Numbers):
    """Residual f with f^2 / 2 = rho(e), smooth (and with finite derivatives) at e = 0."""
    u = e / nb.sigma_r
    a = jnp.abs(u)
    huber = jnp.where(a <= 1.0, u, jnp.sign(u) * jnp.sqrt(jnp.maximum(2.0 * a - 1.0, 1.0)))
    t = u * u  # cauchy: u * sqrt(log1p(t) / t), with the ratio's series near 0
    small = t < 1e-8
    ts = jnp.where(small, 1.0, t)
    cauchy = u * jnp.sqrt(jnp.where(small, 1.0 - 0.5 * t, jnp.log1p(ts) / ts))
    mixture = jnp.sqrt(2.0 * (_mixture_logpdf_bound(nb) - _mixture_logpdf(e, nb)))
    return _select(nb.loss_id, (u, huber, cauchy, mixture))


def _irls_weight(e, nb: _Numbers):
    """IRLS weight psi(e) / e * sigma_r^2 (1 for l2), >= 0; psi = d rho / d e."""
    rho1 = lambda x: _rho(x, nb)  # noqa: E731
    d1 = jax.vmap(jax.grad(rho1))(e)
    d2 = jax.vmap(jax.grad(jax.grad(rho1)))(e)
    small = jnp.abs(e) < 1e-9
    w = jnp.where(small, d2, d1 / jnp.where(small, 1.0, e))
    return jnp.maximum(w, 0.0) * nb.sigma_r**2


# ---------------------------------------------------------------------------------------------
# Model and fit (traced)


class _State(eqx.Module):
    x: Float[Array, "n d"]
    c: Float[Array, ""]
    b: Float[Array, " n"]


def _errors(state: _State, obs: Observations, nb: _Numbers):
    """Range errors e = z - model [m] of every observation."""
    diff = state.x[obs.i] - state.x[obs.j]
    sq = jnp.sum(diff * diff, axis=-1)
    dist = jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)
    model = dist + nb.use_c * state.c + nb.use_b * (state.b[obs.i] + state.b[obs.j])
    return obs.z - model


def _prior_scales(nb: _Numbers):
    """Prior widths [m] of c and b: unused offsets are pinned at zero (keeps full column rank)."""
    sc = jnp.where(nb.use_c > 0, 10.0, 1e-3)
    sb = jnp.where(nb.use_b > 0, nb.node_bias_sigma_m, 1e-3)
    return sc, sb


def _residuals(state: _State, args):
    obs, nb = args
    f = _sqrt_rho(_errors(state, obs, nb), nb) * jnp.sqrt(obs.w)
    sc, sb = _prior_scales(nb)
    return f, state.c / sc, state.b / sb


def _cost(state: _State, args) -> Array:
    f, pc, pb = _residuals(state, args)
    return 0.5 * (jnp.sum(f * f) + pc * pc + jnp.sum(pb * pb))


def _rows(state: _State, args):
    """Every residual of `_residuals` with its local Jacobian and parameter indices (`SparseLevenbergMarquardt`).

    A pair's residual depends on (x_i, x_j, c, b_i, b_j) only; the prior rows on c and on one b_k. Indices
    are into `ravel_pytree(state)` = (x.ravel(), c, b).
    """
    obs, nb = args
    m, dim = state.x.shape
    sc, sb = _prior_scales(nb)

    def pair(u, z, w):
        xi, xj, c, bi, bj = u[:dim], u[dim : 2 * dim], u[2 * dim], u[2 * dim + 1], u[2 * dim + 2]
        one = Observations(jnp.zeros(1, int), jnp.ones(1, int), z[None], w[None])
        st = _State(jnp.stack([xi, xj]), c, jnp.stack([bi, bj]))
        return (_sqrt_rho(_errors(st, one, nb), nb) * jnp.sqrt(one.w))[0]

    u, idx = _local_params(state, obs)
    f = jax.vmap(pair)(u, obs.z, obs.w)
    g = jax.vmap(jax.jacfwd(pair))(u, obs.z, obs.w)
    n_loc = 2 * dim + 3
    # prior rows: c / sc on the c column, b_k / sb on b_k's column (the other local entries are zero)
    g_c = jnp.zeros((1, n_loc)).at[0, 2 * dim].set(1.0 / sc)
    i_c = jnp.full((1, n_loc), m * dim)
    g_b = jnp.zeros((m, n_loc)).at[:, 0].set(1.0 / sb)
    i_b = jnp.broadcast_to((m * dim + 1 + jnp.arange(m))[:, None], (m, n_loc))
    return (
        jnp.concatenate([f, jnp.reshape(state.c / sc, (1,)), state.b / sb]),
        jnp.concatenate([g, g_c, g_b]),
        jnp.concatenate([idx, i_c, i_b]),
    )


def _solver(name: str, tol: float, tail: int = 0):
    """The least-squares solver `name`; `tail`: the per-node offsets (last in the state) enter no residual
    (`bias` other than `node`), which `lm` exploits (`SparseLevenbergMarquardt.diag_tail`)."""
    if name == "gn":
        return optx.GaussNewton(rtol=tol, atol=tol)
    if name == "lm_dense":
        return optx.LevenbergMarquardt(rtol=tol, atol=tol)
    return SparseLevenbergMarquardt(rtol=tol, atol=tol, rows=_rows, diag_tail=tail)


@eqx.filter_jit
def _initial_starts(
    d_pair: Array, w_pair: Array, key: Array, dim: int, init: str, n_starts: int, smacof_iters: int
) -> Array:
    """(S, n, dim) start configurations from classical MDS, SMACOF and random SMACOF starts."""
    n = d_pair.shape[0]
    full = mds.complete_distances(jnp.where(w_pair > 0, d_pair, jnp.nan))
    x_cmds = mds.classical_mds(full, dim)
    # A tiny deterministic jitter breaks the exact degeneracy of a planar MDS in 3-D.
    jitter = 1e-3 * jax.random.normal(jax.random.fold_in(key, 1), x_cmds.shape)
    x_cmds = x_cmds + jitter
    if init == "cmds":
        return x_cmds[None]
    x_sm = mds.smacof(d_pair, w_pair, x_cmds, smacof_iters)
    if init == "smacof":
        return x_sm[None]
    span = jnp.max(jnp.where(jnp.isfinite(full), full, 0.0))
    rand = jax.random.uniform(key, (n_starts, n, dim), minval=-0.5, maxval=0.5) * span
    rand_sm = jax.vmap(lambda x0: mds.smacof(d_pair, w_pair, x0, smacof_iters))(rand)
    return jnp.concatenate([x_cmds[None], x_sm[None], rand_sm], axis=0)


@eqx.filter_jit
def _fit_starts(
    y0s: _State,
    obs: Observations,
    nb: _Numbers,
    solver: str,
    tol: float,
    max_steps: int,
    factors: Array | None = None,
    coarse_tol: float | None = None,
    tail: int = 0,
):
    """Refine every start (a batched `_State`; vmapped least squares); returns final states, costs and
    the outcome codes of their last fits (`jaxcal.solver.outcome`).

    With `factors` (G,) the loss scale is graduated (graduated non-convexity): the fit is solved
    with sigma_r * factors[0], ..., sigma_r * factors[-1] in turn, each warm-started from the last. A wide
    scale first pulls every start towards the bulk of the data before a narrow, redescending loss
    decides which ranges are outliers, so gross errors in the start do not trap the fit. With `coarse_tol`
    (`solver="lm"` only), every stage but the last stops at that tolerance (or `tol`, if looser). `tail`:
    see `_solver` (static; the number of nodes when the model has no per-node offsets, else 0).
    """
    args = (obs, nb)
    factors = jnp.ones(1) if factors is None else factors
    last = jnp.arange(factors.shape[0]) == factors.shape[0] - 1
    coarse = solver == "lm" and coarse_tol is not None

    def one(y0):
        def stage(y, fl):
            factor, is_last = fl
            nbk = eqx.tree_at(lambda t: t.sigma_r, nb, nb.sigma_r * factor)
            if coarse:
                tol_k = jnp.where(is_last, tol, max(tol, coarse_tol))
                opt = SparseLevenbergMarquardt(rtol=tol_k, atol=tol_k, rows=_rows, diag_tail=tail)
            else:
                opt = _solver(solver, tol, tail)
            sol = optx.least_squares(_residuals, opt, y, (obs, nbk), max_steps=max_steps, throw=False)
            return sol.value, S.outcome(sol)

        y, codes = jax.lax.scan(stage, y0, (factors, last))
        return y, _cost(y, args), codes[-1]

    # one start at a time: each stops at its own step count (a vmapped while loop runs every start as
    # long as the slowest, and a batched scatter of the sparse normal equations is slow on CPU)
    return jax.lax.map(one, y0s)


def _procrustes_rmse(x: Array, ref: Array) -> Array:
    """RMSE [m] of `x` after the best rigid motion (rotation and translation, no reflection) onto `ref`."""
    xc, rc = x - jnp.mean(x, axis=0), ref - jnp.mean(ref, axis=0)
    u, _, vt = jnp.linalg.svd(xc.T @ rc)
    d = jnp.sign(jnp.linalg.det(u @ vt))
    r = (u * jnp.concatenate([jnp.ones(x.shape[1] - 1), d[None]])) @ vt  # x @ r ~ ref
    return jnp.sqrt(jnp.mean(jnp.sum((xc @ r - rc) ** 2, axis=1)))


@eqx.filter_jit
def offset_bootstrap(
    state: _State,
    obs: Observations,
    nb: _Numbers,
    key: Array,
    n_boot: int,
    solver: str,
    tol: float,
    max_steps: int,
    tail: int = 0,
) -> Array:
    """Predicted position error of fitting the common range offset c or leaving it out (`bias=auto`).

    A common offset is not always worth estimating: where the geometry is weak (e.g. nearly planar 3-D
    scenes) c trades off against the poorly determined directions, and the variance its estimate adds
    can exceed the bias of ignoring it. Which one wins is estimated by a residual bootstrap of the
    network fit: replicate observations are the fitted model plus residuals resampled with replacement
    (inflated for the degrees of freedom the fit used up); each replicate is refitted locally (from the
    fit) with and without c, and the rigidly aligned position RMSE against the fitted positions is averaged.

    Args:
        state: the network-offset fit (positions (m, D), c, b).
        obs: the observations it was fitted to (padding has weight 0 and is never resampled).
        nb: the numbers of that fit (`use_c` = 1).
        key: PRNG key; n_boot: replicates (static).

    Returns:
        ((2,) RMSE [m] of (with offset, without offset), averaged over the replicates; (n_boot, 2) outcome
        codes of the replicate fits (`jaxcal.solver.outcome`)).
    """
    e = _errors(state, obs, nb)
    model = obs.z - e
    real = obs.w > 0
    logits = jnp.where(real, 0.0, -jnp.inf)
    # Fitted residuals are smaller than the errors by about sqrt((M - P) / M) (P fitted parameters):
    # resample them inflated by the inverse (the usual correction of a regression residual bootstrap).
    m, dim = state.x.shape
    n_par = dim * m - dim * (dim + 1) // 2 + 1 + nb.use_b * m
    n_obs = jnp.sum(real)
    e_boot = e * jnp.sqrt(n_obs / jnp.maximum(n_obs - n_par, 1.0))
    nb_none = eqx.tree_at(lambda t: t.use_c, nb, jnp.zeros_like(nb.use_c))
    start_none = eqx.tree_at(lambda t: t.c, state, jnp.zeros_like(state.c))

    def one(k):
        pick = jax.random.categorical(k, logits, shape=e.shape)
        zb = jnp.where(real, model + e_boot[pick], obs.z)
        obs_b = Observations(obs.i, obs.j, zb, obs.w)

        def fit(y0, nbk):
            sol = optx.least_squares(
                _residuals, _solver(solver, tol, tail), y0, (obs_b, nbk), max_steps=max_steps, throw=False
            )
            return _procrustes_rmse(sol.value.x, state.x) ** 2, S.outcome(sol)

        return jax.tree.map(lambda *a: jnp.stack(a), fit(state, nb), fit(start_none, nb_none))

    sq, codes = jax.vmap(one)(jax.random.split(key, n_boot))
    return jnp.sqrt(jnp.mean(sq, axis=0)), codes


@eqx.filter_jit
def _irls_all(
    y0: _State,
    obs: Observations,
    pair_i: Array,
    pair_j: Array,
    pair_of_obs: Array,
    nb: _Numbers,
    solver: str,
    tol: float,
    max_steps: int,
    n_iter: int,
    tail: int = 0,
) -> _State:
    """Minimise the robust cost over every single range by iteratively reweighted least squares.

    With fixed weights w_k the cost of a pair's ranges, sum_k w_k (z_k - m)^2, equals
    W (zbar - m)^2 + const with W = sum_k w_k and zbar the weighted mean, so each inner
    least-squares problem has one residual per pair whatever the number of epochs. Returns the state
    and the outcome code of the last round's fit (`jaxcal.solver.outcome`).
    """
    n_pairs = pair_i.shape[0]

    def step(state, _):
        e = _errors(state, obs, nb)
        w = _irls_weight(e, nb) * obs.w
        wsum = jax.ops.segment_sum(w, pair_of_obs, n_pairs)
        zbar = jax.ops.segment_sum(w * obs.z, pair_of_obs, n_pairs) / jnp.maximum(wsum, 1e-300)
        pairs = Observations(pair_i, pair_j, zbar, wsum)
        sol = optx.least_squares(
            _residuals,
            _solver(solver, tol, tail),
            state,
            (pairs, nb.with_loss("l2")),
            max_steps=max_steps,
            throw=False,
        )
        return sol.value, S.outcome(sol)

    state, codes = jax.lax.scan(step, y0, None, length=n_iter)
    return state, codes[-1]


@eqx.filter_jit
def _pair_locations(
    state: _State, obs: Observations, pair_i: Array, pair_j: Array, pair_of_obs: Array, nb: _Numbers
) -> Observations:
    """One observation per pair: the IRLS-weighted mean of its ranges at `state` (the pair's robust
    location that the all-epochs fit uses), weight 1 (0 for padding)."""
    n_pairs = pair_i.shape[0]
    w = _irls_weight(_errors(state, obs, nb), nb) * obs.w
    wsum = jax.ops.segment_sum(w, pair_of_obs, n_pairs)
    zbar = jax.ops.segment_sum(w * obs.z, pair_of_obs, n_pairs) / jnp.maximum(wsum, 1e-300)
    return Observations(pair_i, pair_j, zbar, (wsum > 0).astype(zbar.dtype))


def _local_params(state: _State, obs: Observations):
    """Each observation's own parameters u (M, 2D + 3) = (x_i, x_j, c, b_i, b_j) and their indices
    (M, 2D + 3) into `ravel_pytree(state)` = (x.ravel(), c, b): the sparse rows of the Jacobian."""
    m, dim = state.x.shape
    u = jnp.concatenate(
        [
            state.x[obs.i],
            state.x[obs.j],
            jnp.broadcast_to(state.c, obs.i.shape)[:, None],
            state.b[obs.i][:, None],
            state.b[obs.j][:, None],
        ],
        axis=1,
    )
    ax = jnp.arange(dim)
    idx = jnp.concatenate(
        [
            obs.i[:, None] * dim + ax,
            obs.j[:, None] * dim + ax,
            jnp.full((obs.i.shape[0], 1), m * dim),
            m * dim + 1 + obs.i[:, None],
            m * dim + 1 + obs.j[:, None],
        ],
        axis=1,
    )
    return u, idx


def _error_rows(state: _State, obs: Observations, nb: _Numbers):
    """Range errors e (M,) with their local Jacobians (M, 2D + 3) with respect to (x_i, x_j, c, b_i, b_j)
    and those parameters' indices into `ravel_pytree(state)` = (x.ravel(), c, b)."""
    dim = state.x.shape[1]

    def one(u, z):
        st = _State(jnp.stack([u[:dim], u[dim : 2 * dim]]), u[2 * dim], u[2 * dim + 1 :])
        return _errors(st, Observations(jnp.zeros(1, int), jnp.ones(1, int), z[None], jnp.ones(1)), nb)[0]

    u, idx = _local_params(state, obs)
    return jax.vmap(one)(u, obs.z), jax.vmap(jax.grad(one))(u, obs.z), idx


@eqx.filter_jit
def _covariance(free: Array, template: Array, mask: Array, c: Array, b: Array, obs: Observations, nb: _Numbers):
    """Covariance of the free position coordinates (plus offsets) in the anchor frame.

    J^T W J is accumulated from each range's few nonzero derivatives (`sparse_lm.normal_equations`), so
    memory follows the number of parameters squared, not ranges times parameters.

    Returns (cov of free coordinates (F, F), residual sigma^2 [m^2]).
    """
    m, dim = template.shape
    idx = jnp.nonzero(mask.ravel(), size=free.shape[0])[0]
    x = template.ravel().at[idx].set(free).reshape(template.shape)
    e, g, gi = _error_rows(_State(x, c, b), obs, nb)
    n_b = b.shape[0]
    w = _irls_weight(e, nb) * obs.w
    n_par = free.shape[0] + nb.use_c + nb.use_b * n_b
    dof = jnp.maximum(jnp.sum(obs.w) - n_par, 1.0)
    s2 = jnp.sum(w * e * e) / dof
    h_all, _ = normal_equations(e, g * jnp.sqrt(w / s2)[:, None], gi, m * dim + 1 + n_b, chunk=1 << 16)
    sel = jnp.concatenate([idx, m * dim + jnp.arange(1 + n_b)])  # (free coordinates, c, b)
    h = h_all[sel][:, sel]
    # Unused offsets are pinned by a stiff prior; per-node offsets get their Gaussian prior.
    sc, sb = _prior_scales(nb)
    prior = jnp.concatenate([jnp.zeros(free.shape[0]), jnp.stack([1.0 / sc**2]), jnp.full(n_b, 1.0 / sb**2)])
    h = h + jnp.diag(prior)
    cov = jnp.linalg.inv(h)
    f = free.shape[0]
    return cov[:f, :f], s2


def covariance_union(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The covariance a + (b - a)_+ ((.)_+ the positive semi-definite part): at least as large as a and as
    b in every direction (a + (b - a)_+ = b + (b - a)_-), symmetric PSD when a and b are. Coordinates
    where b - a is not finite (a node the pairs do not fix) get NaN rows and columns."""
    a = 0.5 * (a + a.T)
    d = 0.5 * (b + b.T) - a
    # coordinates the ranges do not fix (a singular sandwich: inf / NaN) are undefined: NaN rows and columns
    ok = np.isfinite(d).all(axis=0) & np.isfinite(d).all(axis=1) & (np.abs(d).max(axis=0, initial=0) < 1e150)
    out = np.full_like(a, np.nan)
    if ok.any():
        sub = np.ix_(ok, ok)
        try:
            lam, vec = np.linalg.eigh(d[sub])
        except np.linalg.LinAlgError:
            return out
        out[sub] = a[sub] + (vec * np.maximum(lam, 0.0)) @ vec.T
    return 0.5 * (out + out.T)


def posterior_excess(cov_post: np.ndarray, laplace: np.ndarray, nu: float) -> np.ndarray:
    """What the posterior of `estimate=mean` adds to its own linearisation: (k C - L)_+, with C the
    posterior sample covariance, L the Laplace covariance of the same model with a Gaussian likelihood
    of the same scale s, (J^T W J / s^2 + prior)^-1, and k = (nu + 1) / (nu + 3) the Student-t
    likelihood's Fisher information per pair relative to that Gaussian ((.)_+ the positive semi-definite
    part). Where the ranges fix the nodes to first order k C ~ L and this is ~0 (Monte Carlo noise); where
    the posterior is curved or skewed (a weakly determined direction) it is the width the linearised
    pair covariance (`pair_covariance`) cannot see. The posterior itself is not a covariance of the
    error: it has no per-pair systematic errors that the geometry absorbs, and its Cauchy tails make it
    twice as wide as its scale in every well-determined direction; the union of the two (before) was
    too wide in the family benchmarks (NEES/dof median 0.48-0.56, coverage 98-100 %)."""
    lap = 0.5 * (laplace + laplace.T)
    return covariance_union(lap, (nu + 1.0) / (nu + 3.0) * cov_post) - lap


def _pair_scale(e: Array, real: Array, n_par: Array) -> Array:
    """Robust scale [m] of pair errors: 1.4826 MAD, inflated for the fitted parameters (sqrt(M / (M - P)))."""
    m = jnp.sum(real)
    mad = jnp.nanmedian(jnp.where(real, jnp.abs(e), jnp.nan))
    return jnp.maximum(1.4826 * mad * jnp.sqrt(m / jnp.maximum(m - n_par, 1.0)), 1e-6)


@eqx.filter_jit
def _pair_jacobian(theta: Array, template: Array, mask: Array, obs: Observations, nb: _Numbers):
    """Pair errors e = z - model (M,) at theta = (free coordinates, c, b) and their Jacobian (M, P)
    (`pair_covariance.pair_covariance` takes it; padding rows are zero)."""
    n_f = theta.shape[0] - 1 - template.shape[0]  # theta = (free (n_f,), c, b (m,))
    idx = jnp.nonzero(mask.ravel(), size=n_f)[0]

    def errs(th):
        x = template.ravel().at[idx].set(th[:n_f]).reshape(template.shape)
        return _errors(_State(x, th[n_f], th[n_f + 1 :]), obs, nb)

    real = obs.w > 0
    return jnp.where(real, errs(theta), 0.0), jax.jacfwd(errs)(theta) * real[:, None]


@eqx.filter_jit
def _range_weights(state: _State, obs: Observations, nb: _Numbers) -> Array:
    """IRLS weight of every observation at `state` (0 for padding), for the pair covariance: at most 1, the
    weight of a range under the Gaussian core. (The mixture's psi does not vanish at e = 0, its mode is
    shifted by the NLOS component, so psi(e) / e is singular near e = 0: one pair whose errors sat there
    weighed 10^4 times the others and sized every variance component alone, 10^5 m^2 for 0.3 m errors.)"""
    return jnp.minimum(_irls_weight(_errors(state, obs, nb), nb), 1.0) * obs.w


_LEAPFROG = 16  # leapfrog steps per HMC transition of `posterior_mean`
_BURN = 250  # most transitions of each of the two burn-in phases of `posterior_mean`
_BLOCK = 125  # transitions per block of `posterior_mean` after the burn-in (its stopping rule's unit)


def _split_rhat(s1: Array, s2: Array, n: int) -> Array:
    """Split-chain potential scale reduction R-hat per coordinate (Gelman et al.).

    Args:
        s1, s2: (2, C, P) sums and sums of squares of the two halves of C chains, n draws each.
    """
    mean = (s1 / n).reshape(-1, s1.shape[-1])
    var = ((s2 - s1 * s1 / n) / jnp.maximum(n - 1, 1)).reshape(-1, s1.shape[-1])
    w = jnp.mean(var, axis=0)
    b = n * jnp.var(mean, axis=0, ddof=1)
    var_plus = (n - 1) / n * w + b / n
    return jnp.sqrt(var_plus / jnp.maximum(w, 1e-300))


@eqx.filter_jit
def posterior_mean(
    free: Array,
    template: Array,
    mask: Array,
    c: Array,
    b: Array,
    obs: Observations,
    nb: _Numbers,
    key: Array,
    nu: Array,
    n_chains: int,
    n_steps: int,
    sample_node_offsets: bool = True,
    mcse: float = 0.0,
):
    """Posterior mean and covariance of the free frame coordinates (and offsets) (`estimate=mean`).

    The least-squares / robust fit is the posterior *mode*. Where the geometry is weak (a direction the
    ranges pin down only to second order, e.g. nodes nearly in one plane or on one line), the posterior is
    curved and skewed, and its mode sits away from its mean; the mean is the estimate with the least
    expected squared error. Model: one observation per pair (`obs`, the per-pair median summary), each
    error Student-t with `nu` degrees of freedom and a common scale s = 1.4826 MAD(e) sqrt(M / (M - P)) of
    the fit's pair errors (per-pair systematic errors dominate on real meshes: repeated ranges of a pair
    are not independent, so the pair, not the single range, is the unit); flat prior on positions, the
    offsets' priors of `_prior_scales`. Sampled by Hamiltonian Monte Carlo (`_LEAPFROG` leapfrog steps per
    transition, `n_chains` vmapped chains started at the fit); a quarter of `n_steps` (at most 2 `_BURN`) is burn-in:
    its first half runs whitened by the Laplace covariance and estimates the posterior covariance, which
    whitens the rest; the step size adapts during the burn-in to a mean acceptance probability of 0.8.

    Args:
        free: (F,) free coordinates of the fit; template: (m, D) frame coordinates (fixed ones 0);
        mask: (m, D) bool, which entries of `template` are free; c, b: the fit's offsets;
        obs: pair observations (padding has weight 0); nb: numbers of the fit; key: PRNG key;
        nu: Student-t degrees of freedom; n_chains, n_steps: static sampler sizes.
        mcse: static; > 0: stop after the burn-in once the Monte Carlo error of the mean is below mcse
            posterior sd (and split R-hat below 1.01) in every free coordinate, checked every two blocks of
            `_BLOCK` transitions; 0: run all n_steps.
        sample_node_offsets: static; False when the model has no per-node offsets (`nb.use_b` off): they
            then enter no range, their posterior is their prior (mean 0, sd `node_bias_sigma_m`,
            independent of the rest), and they are returned as such instead of being sampled (P = F + 1
            sampled dimensions instead of F + 1 + n: the whitening costs O(P^2) per gradient).

    Returns:
        (mean (F + 1 + n,), covariance (F + 1 + n, F + 1 + n), acceptance rate, max split R-hat over the
        free coordinates, transitions run per chain (burn-in included), the Laplace covariance of the same
        model with a Gaussian likelihood of the same scale, (J^T W J / s^2 + prior)^-1 at the fit (P, P):
        the linearisation that `solve` compares the samples with).
    """
    f, n_b = free.shape[0], b.shape[0]
    idx = jnp.nonzero(mask.ravel(), size=f)[0]
    b_fixed = jnp.zeros_like(b)
    theta0 = jnp.concatenate([free, jnp.reshape(c, (1,))] + ([b] if sample_node_offsets else []))
    p_dim = theta0.shape[0]

    def errs(theta):
        x = template.ravel().at[idx].set(theta[:f]).reshape(template.shape)
        return _errors(_State(x, theta[f], theta[f + 1 :] if sample_node_offsets else b_fixed), obs, nb)

    real = obs.w > 0
    e0 = errs(theta0)
    n_par = f + nb.use_c + nb.use_b * n_b
    scale = _pair_scale(e0, real, n_par)
    sc, sb = _prior_scales(nb)
    prior_prec = jnp.concatenate([jnp.zeros(f), jnp.stack([1.0 / sc**2]), jnp.full(n_b, 1.0 / sb**2)])
    prior_prec = prior_prec[:p_dim]

    def logp(theta):
        e = errs(theta)
        ll = -0.5 * (nu + 1.0) * jnp.sum(obs.w * jnp.log1p((e / scale) ** 2 / nu))
        return ll - 0.5 * jnp.sum(prior_prec * theta * theta)

    # Hamiltonian Monte Carlo in whitened coordinates theta = center + root @ u: root @ root.T is the
    # Laplace covariance first, then (from the second half of the burn-in on) the burn-in's sample
    # covariance, which follows a curved, weakly determined posterior. The leapfrog step size adapts
    # during the burn-in towards a mean acceptance probability of 0.8.
    jac = jax.jacfwd(errs)(theta0)
    info = (jac.T * obs.w) @ jac / scale**2 + jnp.diag(prior_prec)

    def sqrt_cov(cov):
        lam, vec = jnp.linalg.eigh(0.5 * (cov + cov.T))
        return vec * jnp.sqrt(jnp.maximum(lam, 1e-12 * jnp.max(lam)))

    def transition(carry, k, center, root, adapt):
        u, lp, eps, acc = carry  # u: (C, P) whitened positions, lp: (C,), eps: scalar step size
        k1, k2, k3 = jax.random.split(k, 3)
        lp_u = lambda v: logp(center + root @ v)  # noqa: E731
        grad = jax.vmap(jax.grad(lp_u))
        h = eps * jax.random.uniform(k3, minval=0.8, maxval=1.2)  # jittered step size
        mom = jax.random.normal(k1, u.shape)

        def leap(state, _):  # the gradient at q is carried: one evaluation per leapfrog step, not two
            q, pm, g = state
            pm = pm + 0.5 * h * g
            q = q + h * pm
            g = grad(q)
            pm = pm + 0.5 * h * g
            return (q, pm, g), None

        (q, pm, _), _ = jax.lax.scan(leap, (u, mom, grad(u)), None, length=_LEAPFROG)
        lq = jax.vmap(lp_u)(q)
        log_ratio = lq - lp - 0.5 * jnp.sum(pm * pm - mom * mom, axis=-1)
        log_ratio = jnp.where(jnp.isfinite(log_ratio), log_ratio, -jnp.inf)
        ok = jnp.log(jax.random.uniform(k2, lp.shape)) < log_ratio
        p_acc = jnp.exp(jnp.minimum(log_ratio, 0.0))
        eps = jnp.where(adapt, eps * jnp.exp(jnp.mean(p_acc) - 0.8), eps)
        u = jnp.where(ok[:, None], q, u)
        return (u, jnp.where(ok, lq, lp), eps, acc + ok), center + u @ root.T

    def run(carry, k, n, center, root, adapt):
        def body(state, kk):
            carry, s1, s2, outer = state
            carry, th = transition(carry, kk, center, root, adapt)
            return (carry, s1 + th, s2 + th * th, outer + th.T @ th), None

        zeros = jnp.zeros((n_chains, p_dim))
        carry = (carry[0], carry[1], carry[2], jnp.zeros(n_chains))
        (carry, s1, s2, outer), _ = jax.lax.scan(
            body, (carry, zeros, zeros, jnp.zeros((p_dim, p_dim))), jax.random.split(k, n)
        )
        return carry, s1, s2, outer

    def moments(s1, outer, n):
        mean = jnp.sum(s1, axis=0) / n
        return mean, outer / n - jnp.outer(mean, mean)

    def rewhiten(carry, center, root, new_center, new_root):
        th = center + carry[0] @ root.T
        u = jnp.linalg.solve(new_root, (th - new_center).T).T
        lp = jax.vmap(lambda v: logp(new_center + new_root @ v))(u)
        return (u, lp, carry[2], carry[3])

    k0, kb1, kb2, ka = jax.random.split(key, 4)
    lap = jnp.linalg.inv(info)
    root = sqrt_cov(lap)
    u0 = 0.1 * jax.random.normal(k0, (n_chains, p_dim))
    carry = (u0, jax.vmap(lambda v: logp(theta0 + root @ v))(u0), jnp.asarray(0.5 / p_dim**0.25), jnp.zeros(n_chains))
    # burn-in: a quarter of n_steps, at most 2 _BURN (the stopping rule after it decides how long to sample)
    burn1 = min(n_steps // 8, _BURN)
    burn2 = min(n_steps // 4 - n_steps // 8, _BURN)
    carry, s1, _, outer = run(carry, kb1, burn1, theta0, root, True)
    center, cov_burn = moments(s1, outer, burn1 * n_chains)
    new_root = sqrt_cov(cov_burn + jnp.diag(1e-12 + 1e-9 * jnp.diag(cov_burn)))
    carry = rewhiten(carry, theta0, root, center, new_root)
    root = new_root
    carry, _, _, _ = run(carry, kb2, burn2, center, root, True)
    # After the burn-in: blocks of `block` transitions, up to the rest of n_steps; with `mcse` > 0 the
    # sampler stops at an even number of blocks (>= 4) once the Monte Carlo error of the mean, estimated
    # from the spread of the chains' means, is below mcse posterior sd and split R-hat below 1.01 in
    # every free coordinate (a well-determined posterior mixes in a few hundred transitions; the
    # whitened gradient costs O(P^2) each).
    n_blk = max(2 * ((n_steps - burn1 - burn2) // (2 * _BLOCK)), 2)
    block = (n_steps - burn1 - burn2) // n_blk
    zeros_blk = jnp.zeros((n_blk, n_chains, p_dim))
    ids = jnp.arange(n_blk)

    def split(k, s):  # the (2, C, P) sums of the first and the second half of the k blocks run
        first = (ids < k // 2)[:, None, None]
        second = ((ids >= k // 2) & (ids < k))[:, None, None]
        return jnp.stack([jnp.sum(jnp.where(first, s, 0.0), axis=0), jnp.sum(jnp.where(second, s, 0.0), axis=0)])

    def converged(k, s1k, s2k):
        h1, h2 = split(k, s1k), split(k, s2k)
        n_half = (k // 2) * block
        rhat = jnp.max(_split_rhat(h1[..., :f], h2[..., :f], n_half))
        chain_mean = (h1[0] + h1[1]) / (2 * n_half)  # (C, P)
        var = jnp.sum(h2[0] + h2[1], axis=0) / (2 * n_half * n_chains) - jnp.mean(chain_mean, axis=0) ** 2
        err2 = jnp.var(chain_mean, axis=0, ddof=1) / n_chains  # squared Monte Carlo error of the mean
        small = jnp.all(err2[:f] <= mcse**2 * jnp.maximum(var[:f], 1e-300))
        return (k >= 4) & (k % 2 == 0) & (rhat < 1.01) & small

    def more(state):
        _, k, s1k, s2k, _ = state
        return (k < n_blk) & ~((mcse > 0) & converged(k, s1k, s2k))

    def one_block(state):
        carry, k, s1k, s2k, outer = state
        carry, s1, s2, o = run(carry, jax.random.fold_in(ka, k), block, center, root, False)
        accepted = carry[3] + state[0][3]  # run() restarts the acceptance count
        return ((carry[0], carry[1], carry[2], accepted), k + 1, s1k.at[k].set(s1), s2k.at[k].set(s2), outer + o)

    carry = (carry[0], carry[1], carry[2], jnp.zeros(n_chains))
    carry, k, s1k, s2k, outer = jax.lax.while_loop(
        more, one_block, (carry, jnp.asarray(0), zeros_blk, zeros_blk, jnp.zeros((p_dim, p_dim)))
    )
    n_draws = k * block
    accept = jnp.sum(carry[3]) / (n_draws * n_chains)
    mean, cov = moments(jnp.sum(s1k, axis=0), outer, n_draws * n_chains)
    rhat = _split_rhat(split(k, s1k)[..., :f], split(k, s2k)[..., :f], (k // 2) * block)
    cov = 0.5 * (cov + cov.T)
    if not sample_node_offsets:  # append the node offsets' prior: mean 0, variance sb^2, uncorrelated
        mean = jnp.concatenate([mean, b_fixed])
        cov = jax.scipy.linalg.block_diag(cov, jnp.eye(n_b) * sb**2)
    return mean, cov, accept, jnp.max(rhat), burn1 + burn2 + n_draws, lap


# ---------------------------------------------------------------------------------------------
# Public entry points


def posterior_defect(
    i: np.ndarray,
    j: np.ndarray,
    n_nodes: int,
    dim: int,
    nu: float,
    n_offsets: int,
    node_ids: tuple[str, ...],
    seed: int = 0,
) -> str:
    """Why the pair-level posterior of `estimate=mean` cannot be sampled, from the measurement graph
    alone ("" when it can). Decided before sampling, so the fallback does not hang on a chain's path.

    Two structural defects:
    - a node with k distinct neighbours has, far from them, a likelihood that decays like
      r^(-k (nu + 1)) (Student-t tails) over a volume growing like r^(dim - 1): with k (nu + 1) <= dim
      the posterior (flat prior) is improper: its mean and covariance do not exist.
    - the pairs do not fix the configuration to first order: the rigidity matrix (one row per measured
      pair, d||x_i - x_j|| / dx at a random generic configuration) has rank below
      dim n - dim (dim + 1) / 2 (generic rigidity), or there are fewer pairs than unknowns (positions and
      offsets); the posterior then spreads along a continuum and its mean is no estimate.

    Args:
        i, j: (M,) node indices (0..n_nodes-1) of the measured unordered pairs (no duplicates needed).
        n_nodes: number of (connected) nodes; dim: 2 or 3; nu: Student-t degrees of freedom;
        n_offsets: fitted range offsets (common and per-node) that the pairs must also fix;
        node_ids: ids of the n_nodes nodes (for the message); seed: of the random configuration.

    Returns:
        A one-line reason, or "".
    """
    pairs = {
        (min(a, b), max(a, b)) for a, b in zip(np.asarray(i).tolist(), np.asarray(j).tolist(), strict=False) if a != b
    }
    nbrs = [set() for _ in range(n_nodes)]
    for a, b in pairs:
        nbrs[a].add(b)
        nbrs[b].add(a)
    for k in range(n_nodes):
        if len(nbrs[k]) * (nu + 1.0) <= dim:
            names = ", ".join(node_ids[q] for q in sorted(nbrs[k]))
            return (
                f"{node_ids[k]} ranges only {names}: its posterior under the Student-t likelihood "
                f"(nu={nu:g}) is improper"
            )
    n_unknown = dim * n_nodes - dim * (dim + 1) // 2
    if len(pairs) < n_unknown + n_offsets:
        return f"{len(pairs)} measured pairs for {n_unknown + n_offsets} unknowns"
    x = np.random.default_rng(seed).normal(size=(n_nodes, dim))
    rig = np.zeros((len(pairs), n_nodes * dim))
    for row, (a, b) in enumerate(sorted(pairs)):
        u = (x[a] - x[b]) / np.linalg.norm(x[a] - x[b])
        rig[row, a * dim : (a + 1) * dim] = u
        rig[row, b * dim : (b + 1) * dim] = -u
    if np.linalg.matrix_rank(rig) < n_unknown:
        return "the measured pairs do not make the network rigid (it can flex without changing a range)"
    return ""


def _bucket(m: int) -> int:
    """Padded length >= m from the sequence 16, 24, 32, 48, 64, ... (fewer distinct shapes to compile)."""
    size = 16
    while size < m:
        size = size * 3 // 2 if size & (size - 1) == 0 else size * 4 // 3
    return size


def _pad(a: np.ndarray, size: int) -> np.ndarray:
    """`a` padded with zeros to `size` (padded observations get weight 0 and contribute nothing)."""
    return np.concatenate([a, np.zeros(size - a.shape[0], dtype=a.dtype)])


def _active_nodes(i: np.ndarray, j: np.ndarray, n: int, a0: int) -> np.ndarray:
    """Boolean (N,) mask of the nodes connected to a0 through measured pairs."""
    adj = [[] for _ in range(n)]
    for u, v in zip(i.tolist(), j.tolist(), strict=False):
        adj[u].append(v)
        adj[v].append(u)
    seen = np.zeros(n, dtype=bool)
    stack = [a0]
    seen[a0] = True
    while stack:
        u = stack.pop()
        for v in adj[u]:
            if not seen[v]:
                seen[v] = True
                stack.append(v)
    return seen


def _pair_matrix(obs: Observations, m: int) -> np.ndarray:
    """(m, m) symmetric weights of the measured pairs (0 = not measured) of one-per-pair observations."""
    w = np.zeros((m, m))
    oi, oj, ow = np.asarray(obs.i), np.asarray(obs.j), np.asarray(obs.w)
    w[oi, oj] = w[oj, oi] = np.where(ow > 0, ow, w[oi, oj])
    return w


def _sqrt_rho_of(nb: _Numbers, e: Array) -> Array:
    return _sqrt_rho(e, nb)


def _rho_of(nb: _Numbers, e: Array) -> Array:
    return _rho(e, nb)


def _relocation_candidates(state: _State, table, nb: _Numbers, grid_n: int, n_cand: int) -> _State:
    """Batched starts of one relocation round: `state` with one node moved to another basin, for the
    `n_cand` nodes whose locally refined move lowers the total cost most (every node when m <= n_cand)."""
    m = state.x.shape[0]
    nbr, d_nbr, w_nbr = (jnp.asarray(a) for a in table)
    # Score grid points with a loss no narrower than the grid spacing, or the true basin can be missed
    # between two grid points; the refinement after the move uses the real scale.
    lo, hi = jnp.min(state.x, axis=0), jnp.max(state.x, axis=0)
    spacing = 1.5 * jnp.max(hi - lo) / (grid_n - 1)  # grid span: the scene plus a quarter on either side
    nb_grid = eqx.tree_at(lambda t: t.sigma_r, nb, jnp.maximum(nb.sigma_r, spacing))
    offset = nb.use_c * state.c + nb.use_b * (state.b[:, None] + state.b[nbr])
    moved, delta = relocation_moves(
        state.x,
        offset,
        nbr,
        d_nbr,
        w_nbr,
        jax.tree_util.Partial(_rho_of, nb_grid),
        jax.tree_util.Partial(_sqrt_rho_of, nb),
        grid_n,
        3.0 * nb_grid.sigma_r,
    )
    delta = np.where(np.isfinite(np.asarray(delta)), np.asarray(delta), np.inf)
    pick = np.arange(m) if m <= n_cand else np.argsort(delta, kind="stable")[:n_cand]
    xs = jnp.repeat(state.x[None], pick.size, axis=0).at[np.arange(pick.size), pick].set(moved[pick])
    return _State(xs, jnp.broadcast_to(state.c, (pick.size,)), jnp.broadcast_to(state.b, (pick.size, m)))


def stage_count(params: BatchParams) -> int:
    """Stages `solve` reports to its `progress` callback: multi-start fit, relocation, offset choice
    (bias=auto), all-ranges refinement (summary=all), covariance, posterior sampler (estimate=mean)."""
    p = params
    return 3 + (p.bias == "auto") + (p.summary == "all") + (p.estimate == "mean")


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

    Returns:
        A `BatchSolution` in the anchor frame.

    Raises:
        JaxcalError: when a0, a1 or a2 are not connected by ranges, or fewer than dim + 1 nodes are.
    """
    p = params or BatchParams()
    done = progress or (lambda k: None)  # one call per finished stage (`stage_count`)
    r = np.asarray(range_m, dtype=np.float64)
    if r.ndim != 3 or r.shape[1] != r.shape[2]:
        raise JaxcalError(f"batch: expected ranges of shape (K, N, N), got {r.shape}")
    n = r.shape[1]
    ids = node_ids or tuple(str(k) for k in range(n))
    a0, a1, a2 = anchors
    i_m, j_m, z_m, w_m = observations(r, "median")
    pw = spread_weights(r) if p.pair_weight == "spread" else None
    if pw is not None:
        w_m = pw[i_m, j_m]
    if z_m.size == 0:
        raise JaxcalError("batch: the dataset has no finite ranges")
    active = _active_nodes(i_m, j_m, n, a0)
    for a in (a1, a2):
        if not active[a]:
            raise JaxcalError(f"batch: frame node {ids[a]!r} has no ranges connecting it to a0 {ids[a0]!r}")
    if active.sum() < p.dim + 1:
        raise JaxcalError(f"batch: need at least {p.dim + 1} connected nodes, got {int(active.sum())}")
    sub = np.flatnonzero(active)
    remap = -np.ones(n, dtype=np.int64)
    remap[sub] = np.arange(sub.size)
    m = len(sub)

    def to_obs(i, j, z, w):
        keep = active[i] & active[j]
        size = _bucket(int(keep.sum()))
        return Observations(
            *(
                jnp.asarray(_pad(a, size))
                for a in (remap[i[keep]], remap[j[keep]], z[keep].astype(float), w[keep].astype(float))
            )
        )

    obs_med = to_obs(i_m, j_m, z_m, w_m)
    d_pair = np.full((m, m), np.nan)
    real = np.asarray(obs_med.w) > 0
    mi, mj, mz = np.asarray(obs_med.i)[real], np.asarray(obs_med.j)[real], np.asarray(obs_med.z)[real]
    d_pair[mi, mj] = mz
    d_pair[mj, mi] = mz
    w_pair = np.isfinite(d_pair).astype(float)
    nb = _Numbers.of(p)
    key = jax.random.PRNGKey(p.seed)
    # a fixed number of starts whatever N: relocation (below) repairs the nodes that no start placed well
    x0s = _initial_starts(
        jnp.asarray(np.nan_to_num(d_pair)), jnp.asarray(w_pair), key, p.dim, p.init, p.n_starts, p.smacof_iters
    )
    if extra_starts is not None:
        x0s = jnp.concatenate([x0s, jnp.asarray(_extra_starts(extra_starts, sub, np.asarray(x0s[0]), p.dim))])
    s_count = x0s.shape[0]
    y0s = _State(x0s, jnp.zeros(s_count), jnp.zeros((s_count, m)))
    gnc = jnp.asarray(2.0 ** np.arange(p.gnc_stages - 1, -1, -1), dtype=float)
    tail = 0 if p.bias == "node" else m  # per-node offsets that enter no range: solved apart (`_solver`)
    states, costs, fit_codes = _fit_starts(y0s, obs_med, nb, p.solver, p.tol, p.max_steps, gnc, p.gnc_tol, tail)
    costs = np.where(np.isfinite(np.asarray(costs)), np.asarray(costs), np.inf)
    best = int(np.argmin(costs))
    state, code = jax.tree.map(lambda a: a[best], states), fit_codes[best]  # code: of the fit `state` is
    cost = float(costs[best])
    done(1)
    grid_n = p.relocate_grid if p.dim == 2 else max(p.relocate_grid // 3, 2)
    table = neighbour_table(d_pair, _pair_matrix(obs_med, m))
    for _ in range(p.relocate_rounds):
        starts = _relocation_candidates(state, table, nb, grid_n, p.relocate_candidates)
        if starts.x.shape[0] < s_count:  # same batch size as the multi-start fit: one compilation serves both
            starts = jax.tree.map(lambda a: jnp.concatenate([a, a[:1].repeat(s_count - a.shape[0], axis=0)]), starts)
        # the multi-start fit's stages and tolerances (one compilation serves both): every stage at the
        # narrow loss, all but the last stopping at gnc_tol
        moved, moved_costs, moved_codes = _fit_starts(
            starts, obs_med, nb, p.solver, p.tol, p.max_steps, jnp.ones_like(gnc), p.gnc_tol, tail
        )
        moved_costs = np.where(np.isfinite(np.asarray(moved_costs)), np.asarray(moved_costs), np.inf)
        k = int(np.argmin(moved_costs))
        if not moved_costs[k] < cost - 1e-9 * max(1.0, abs(cost)):
            break
        state, cost, code = jax.tree.map(lambda a, k=k: a[k], moved), float(moved_costs[k]), moved_codes[k]
    done(1)
    chosen, boot, boot_codes = ("network" if p.bias == "auto" else p.bias), np.full(2, np.nan), np.zeros(0)
    if p.bias == "auto":
        boot, boot_codes = (
            np.asarray(a)
            for a in offset_bootstrap(
                state, obs_med, nb, jax.random.fold_in(key, 7), p.n_boot, p.solver, p.tol, p.max_steps, tail
            )
        )
        if boot[1] < boot[0]:  # leaving the offset out is predicted to place the nodes better
            chosen = "none"
            nb = eqx.tree_at(lambda t: t.use_c, nb, jnp.zeros_like(nb.use_c))
            start = eqx.tree_at(lambda t: t.c, state, jnp.zeros_like(state.c))
            starts = jax.tree.map(lambda a: jnp.repeat(a[None], s_count, axis=0), start)
            refit, _, refit_codes = _fit_starts(
                starts, obs_med, nb, p.solver, p.tol, p.max_steps, jnp.ones_like(gnc), p.gnc_tol, tail
            )
            state, code = jax.tree.map(lambda a: a[0], refit), refit_codes[0]
        done(1)
    obs = obs_pairs = obs_med  # obs_pairs: what the posterior of estimate=mean sees, one per pair
    if p.summary == "all":
        i_a, j_a, z_a, w_a = observations(r, "all")
        obs = to_obs(i_a, j_a, z_a, w_a if pw is None else pw[i_a, j_a])
        oi, oj = np.asarray(obs.i), np.asarray(obs.j)
        key_pair = np.minimum(oi, oj) * m + np.maximum(oi, oj)  # padding maps to pair (0, 0), weight 0
        uniq, pair_of_obs = np.unique(key_pair, return_inverse=True)
        size = _bucket(uniq.size)
        pair_i, pair_j = jnp.asarray(_pad(uniq // m, size)), jnp.asarray(_pad(uniq % m, size))
        state, code = _irls_all(
            state, obs, pair_i, pair_j, jnp.asarray(pair_of_obs), nb, p.solver, p.tol, p.max_steps, p.irls_iters, tail
        )
        if p.estimate == "mean":  # the posterior's pair observations: where the all-ranges fit puts them
            obs_pairs = _pair_locations(state, obs, pair_i, pair_j, jnp.asarray(pair_of_obs), nb)
        jax.block_until_ready(state.x)
        done(1)

    x_sub = np.asarray(state.x)
    x_frame_sub = to_frame(x_sub, int(remap[a0]), int(remap[a1]), int(remap[a2]))
    if p.dim == 3:
        # Ranges cannot tell a 3-D scene from its mirror image through the a0-a1-a2 plane; pick the
        # one where the other nodes lie mostly above it (z up), or below with z_up=false.
        others = np.ones(m, dtype=bool)
        others[[remap[a0], remap[a1], remap[a2]]] = False
        zsum = float(np.sum(x_frame_sub[others, 2]))
        if (zsum < 0) == p.z_up:
            x_frame_sub[:, 2] *= -1.0
    # Gauge-fixed coordinates: a0 fixed; a1 only x; in 3-D a2 has no z.
    mask = np.ones((m, p.dim), dtype=bool)
    mask[remap[a0], :] = False
    mask[remap[a1], 1:] = False
    if p.dim == 3:
        mask[remap[a2], 2] = False
    x_frame_sub[~mask] = 0.0
    free = x_frame_sub[mask]
    cov_free, s2 = _covariance(
        jnp.asarray(free), jnp.asarray(x_frame_sub), jnp.asarray(mask), state.c, state.b, obs, nb
    )
    cov_free = np.asarray(cov_free)
    done(1)
    cov_model = cov_free
    offset, node_b, accept, rhat = float(state.c), np.asarray(state.b), float("nan"), float("nan")
    transitions = 0
    used, reason = "map", ""
    if p.estimate == "mean":
        n_off = int(chosen != "none")  # per-node offsets have a proper prior of their own
        reason = posterior_defect(mi, mj, m, p.dim, p.student_nu, n_off, tuple(ids[k] for k in sub), p.seed)
    if p.estimate == "mean" and not reason:
        mean, cov_s, acc, rh, n_run, lap_s = posterior_mean(
            jnp.asarray(free),
            jnp.asarray(x_frame_sub),
            jnp.asarray(mask),
            state.c,
            state.b,
            obs_pairs,
            nb,
            jax.random.fold_in(key, 11),
            jnp.asarray(float(p.student_nu)),
            p.mcmc_chains,
            p.mcmc_steps,
            chosen == "node",
            float(p.mcmc_mcse),
        )
        f = free.size
        mean, cov_s = np.asarray(mean), np.asarray(cov_s)
        accept, rhat, transitions = float(acc), float(rh), int(n_run)
        done(1)
        if rhat <= RHAT_MAX and np.isfinite(mean).all() and np.isfinite(cov_s).all():
            x_frame_sub[mask] = mean[:f]
            cov_model, offset, node_b = cov_s[:f, :f], float(mean[f]), mean[f + 1 :]
            excess = posterior_excess(cov_model, np.asarray(lap_s)[:f, :f], float(p.student_nu))
            used = "mean"
        else:
            reason = f"the posterior chains did not mix (split R-hat {rhat:.2f}, limit {RHAT_MAX:.2f})"
    # Per-pair systematic errors, sized from the data (`pair_covariance`), at the estimate reported: the
    # pair medians (they do not depend on the fit), each pair weighted as the fit weighs its ranges.
    at = _State(jnp.asarray(x_frame_sub), jnp.asarray(offset), jnp.asarray(node_b))
    theta = jnp.concatenate([jnp.asarray(x_frame_sub[mask]), jnp.reshape(at.c, (1,)), at.b])
    e_pair, jac_pair = (
        np.asarray(a) for a in _pair_jacobian(theta, jnp.asarray(x_frame_sub), jnp.asarray(mask), obs_med, nb)
    )
    w_obs = np.asarray(_range_weights(at, obs, nb))
    oi, oj = np.asarray(obs.i), np.asarray(obs.j)
    w_key = np.bincount(np.minimum(oi, oj) * m + np.maximum(oi, oj), weights=w_obs, minlength=m * m)
    w_pair = w_key[mi * m + mj]  # obs_med: i < j, real rows first
    n_real = mi.size
    sc, sb = _prior_scales(nb)
    prior = np.concatenate([np.zeros(free.size), [1.0 / float(sc) ** 2], np.full(m, 1.0 / float(sb) ** 2)])
    ok = w_pair > 0
    cov_pair, _ = pair_covariance(
        jac_pair[:n_real][ok],
        e_pair[:n_real][ok],
        w_pair[ok],
        pair_spread(r, sub[mi[ok]], sub[mj[ok]]),
        mi[ok],
        mj[ok],
        m,
        prior,
    )
    if used == "mean":  # the pair covariance plus what the posterior adds to its own linearisation
        cov_free = covariance_union(excess, excess + cov_pair[: free.size, : free.size])
    else:  # the Laplace covariance of the all-ranges fit, widened to the pair covariance
        cov_free = covariance_union(cov_model, cov_pair[: free.size, : free.size])
    full_idx = np.flatnonzero(mask.ravel())

    def per_node(cov_f):  # (F, F) over the free coordinates -> (N, D, D) blocks, NaN where undefined
        cov_all = np.zeros((m * p.dim, m * p.dim))
        cov_all[np.ix_(full_idx, full_idx)] = cov_f
        blocks = np.stack([cov_all[k * p.dim : (k + 1) * p.dim, k * p.dim : (k + 1) * p.dim] for k in range(m)])
        blocks = 0.5 * (blocks + np.swapaxes(blocks, 1, 2))
        blocks[~np.isfinite(blocks).all(axis=(1, 2))] = np.nan
        out = np.full((n, p.dim, p.dim), np.nan)
        out[sub] = blocks
        return out

    position = np.full((n, p.dim), np.nan)
    position[sub] = x_frame_sub
    covariance = per_node(cov_free)
    node_off = np.full(n, np.nan)
    node_off[sub] = node_b if chosen == "node" else 0.0
    return BatchSolution(
        position=position,
        covariance=covariance,
        offset_m=offset if chosen != "none" else 0.0,
        node_offset_m=node_off,
        cost=cost,
        start_costs=costs,
        residual_sigma_m=float(np.sqrt(s2)),
        bias=chosen,
        boot_rmse_m=boot,
        mcmc_accept=accept,
        mcmc_rhat=rhat,
        estimate=used,
        fallback_reason=reason,
        model_covariance=per_node(cov_model),
        solver_codes=np.append(np.asarray(code), boot_codes).astype(int),
        mcmc_transitions=transitions,
    )


def _extra_starts(starts: np.ndarray, sub: np.ndarray, base: np.ndarray, dim: int) -> np.ndarray:
    """(E, N, D) user starts -> (2E, m, dim) on the connected nodes: NaN rows from `base`, plus mirror images."""
    ex = np.asarray(starts, dtype=np.float64)
    if ex.ndim == 2:
        ex = ex[None]
    ex = ex[:, sub, :dim]
    if ex.shape[-1] < dim:  # 2-D modes for a 3-D fit: z from the MDS start
        ex = np.concatenate(
            [ex, np.broadcast_to(base[None, :, ex.shape[-1] :], ex.shape[:2] + (dim - ex.shape[-1],))], axis=-1
        )
    ex = np.where(np.isfinite(ex), ex, base[None])
    mirror = ex.copy()
    mirror[..., 1] *= -1.0
    return np.concatenate([ex, mirror])


def warn_if_unmixed(sol: BatchSolution, p: BatchParams) -> bool:
    """Log one warning line (logger `jaxcal`) when `estimate=mean` fell back to the fit; True if so."""
    if p.estimate != "mean" or sol.estimate == "mean":
        return False
    hint = "add ranges"
    if "R-hat" in sol.fallback_reason:
        hint = f"raise mcmc_steps (now {p.mcmc_steps}) or add ranges"
    logging.getLogger("jaxcal").warning(
        "batch: %s: reporting the fit (estimate=map) and its covariance instead; %s",
        sol.fallback_reason or "the posterior mean is not available",
        hint,
    )
    return True


def check_solver(sol: BatchSolution, p: BatchParams, method: str = "batch") -> S.SolverReport:
    """The outcome of the fits `sol` rests on (`BatchSolution.solver_codes`), with one warning line (logger
    `jaxcal`) when one of them did not converge; its `params()` go into the Result params."""
    rep = S.report(sol.solver_codes, "fits")
    rep.warn(method, f"raise max_steps (now {p.max_steps}) or tol (now {p.tol:g})")
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
    from jaxcal.mesh import identify

    p = with_overrides(BatchParams(), params)
    anchors = dataset.config(config)
    empty = identify.undetermined_frame_result(dataset, anchors, "batch", p.dim, as_dict(p))
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
    return identify.mask_result(res, dataset.range)
