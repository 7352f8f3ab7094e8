"""Gaussian-process anchor calibration (paper 001, Sec. III-C), vectorised over anchors.

Per anchor, a GP regresses a target derived from the range over the tag positions:

- `target="range"`: the range itself (the paper's text), with a constant mean equal to the mean of
  training ranges, so that far from the data the prediction reverts to a typical (large) range and
  the search for the *smallest* predicted range stays near the data;
- `target="inv-log"`: y = 1 / log10(sqrt(r) + 1) with a zero mean (the public code): large near the
  anchor, decaying to the prior mean 0 far away; the search looks for the *largest* prediction.

Kernel: Matern with smoothness `nu` plus white noise. nu = 1/2, 3/2, 5/2 use their closed forms; any
other non-integer nu (e.g. the public code's 5/3) uses the general form
`k(r) = s^2 2^(1-nu) / Gamma(nu) z^nu K_nu(z)`, `z = sqrt(2 nu) r / l`, with
`K_nu = pi / (2 sin(nu pi)) (I_-nu - I_nu)` summed as two power series in z^2 (no square root,
smooth
at r = 0) for z <= 9 and the large-z asymptotic expansion beyond (see `matern`). The cancellation of
the series costs at most ~1e-10 absolute in k / s^2, below the jitter.

Hyperparameters (log length scale, log signal variance, log noise variance) maximise the marginal
likelihood: `optx.minimise` with BFGS on the negative log marginal likelihood, per anchor (anchors
in
one jitted `lax.map`: every anchor shares the shapes, padded and masked).

Anchor search (the paper's iterative cuboid search): a regular G^3 grid in a cuboid around the data
(bounding box of the anchor's tag positions plus `margin_m`); the `top_k` (10) best grid samples are
averaged, the cuboid is shrunk by `shrink` around that average, and this repeats until the half size
is below `tol_m` (a static number of rounds, `lax.scan`). When an anchor's tag positions are planar
(`common.is_planar`), z is not observable from positions in the plane: the search runs in the
plane and the height above it is the predicted range at the found point (side `side`).

Large recordings: the training set of each anchor is a stratified subsample by measured range
(`n_bins` equal-width range bins, equal quotas, leftovers filled at random), at most `n_train`
ranges
(the paper's "layered random sampling"). With `stages=2` (default) a second GP is fitted to the
`n_train` shortest ranges of the anchor and searched in a cuboid around the first estimate (the
paper's "first fitting initial points at a coarse scale", then refining). What the subsample costs
in accuracy is measured by benchmarks/gp_subsampling.py. No inducing points.

Gradient search (`search="gradient"`, not the paper's): the minimum of the constant-mean GP lies
where the GP has data, so the cuboid search cannot reach an anchor outside the region the platform
covered (and a planar route then puts the whole range into the height). `gradient_step` instead
uses the eikonal property of a range field, |grad r| = 1 with grad r pointing away from the anchor:
from each of the `top_k` training inputs with the smallest predicted range, a = p - r(p) grad r(p)
with r and grad r from the GP posterior mean (autodiff of the kernel), read where the GP is
supported by data. The step is local (a few gradients; sparse inputs such as hymn's 48 survey
points can give a wrong one), so the answer is the option most consistent with the GP's whole
range field (`range_consistency`: robust spread of r(p_i) - |p_i - a| over the inputs) among the
candidates' mean, each candidate and the cuboid search's answer; its covariance is the candidates'
spread plus the posterior variance term below. Not the default: it helps where the anchors lie
outside the covered region and hurts where sparse inputs give wrong local steps (per-dataset errors
of both searches: the benchmarks page of the docs, `benchmarks/trajectory_calibration.py`).

Covariance of an estimate: the sample covariance of the top-k samples of the last round plus the
GP's posterior variance of the range at the estimate times the identity (for `inv-log`, mapped to
metres by the derivative of the inverse transform): a cone of slope 1 shifted by one posterior
standard deviation moves its apex by about as much.

Parametric mean (`mean="anchor"`, the default; `jaxcal.trajectory.gp_anchor`): the constant-mean
GP above has no notion of where the anchor is: the cuboid search minimises the GP's extrapolation
when the anchor lies outside the region the tag covers, and the height is barely observable from
near-planar trajectories (mean anchor errors of 4-8 m on the real recordings). `model="subsample"`
(the default until the fourteenth round) models r = |p - a| + b + f(p) + e with the anchor a as a mean
parameter, seeded and bounded by `nls`, with a heavy-tailed (Cauchy-weighted) white noise e, on a
stratified subsample (or, with
`block`, every range under a block-diagonal covariance over stretches of consecutive ranges); see
that module. `mean="constant"` keeps the paper's GP and its searches. `model="path"`
(`jaxcal.trajectory.gp_path`, an option): the GP as the noise model of every range, f a Matern GP along
the path's arc length, its marginal likelihood by a Kalman filter in O(n), no fuse or bound.
`model="space"` (`jaxcal.trajectory.gp_space`, an option): the same over the horizontal position, f a
Matern GP on a Hilbert-space basis (O(n m^2) once, then O(n m) per step), for routes driven in laps.
`model="excess"` (`jaxcal.trajectory.gp_excess`, the default since the fourteenth round): every range (at most
`excess_max_ranges` per anchor, evenly spaced in time), the residual a one-sided NLOS excess (a skewed LOS / NLOS
mixture whose NLOS probability is a field over route cells), no fuse or bound: better than `nls` on simulated
NLOS zones, under drift and on hanyang NLOS, within 1.2x on the shared recordings (docs/benchmarks/trajectory.md,
thirteenth and fourteenth rounds).

tinygp is not used: it would add a dependency for a dense GP with one kernel, and its Matern kernels
are the half-integer ones only (no nu = 5/3).
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float

from jaxcal import solver as S
from jaxcal.blas_threads import one_blas_thread
from jaxcal.data import Result
from jaxcal.errors import JaxcalError
from jaxcal.params import with_overrides
from jaxcal.precision import in_float64
from jaxcal.trajectory.common import TrajectoryParams, finish, is_planar, report_fits
from jaxcal.trajectory.drift import MODELS
from jaxcal.trajectory.gp_anchor import MeanModel, cone_spread, fit_mean_model, mean_model_nlml
from jaxcal.trajectory.gp_kernel import (
    Hyper,
    _cone,
    _gram,
    _sqdist,
    from_target,
    matern,
    neg_log_marginal_likelihood,
    stratified_subsample,
    to_target,
)
from jaxcal.trajectory.nls import prepare_offset

__all__ = [
    "GPParams",
    "matern",
    "Hyper",
    "neg_log_marginal_likelihood",
    "fit_hyper",
    "predict",
    "search_anchor",
    "gradient_step",
    "range_consistency",
    "stratified_subsample",
    "to_target",
    "from_target",
    "MeanModel",
    "mean_model_nlml",
    "fit_mean_model",
    "cone_spread",
    "calibrate",
]


class GPParams(TrajectoryParams):
    """Parameters of `gp` (defaults).

    Attributes:
        target: `range` (paper text) or `inv-log` (public code: 1 / log10(sqrt(r) + 1)).
        mean: `anchor` (default: parametric mean |p - a| + b fitted jointly with the kernel by the
            marginal likelihood, seeded and bounded by `nls`; `gp_anchor`) or `constant` (the
            paper: sample mean of the ranges, zero for `inv-log`, then the cuboid search).
        nu: Matern smoothness (1.5 as in the paper; 5/3 as in the public code).
        n_train: training ranges per anchor (stratified subsample by range); n_bins: range strata.
        seed: subsampling seed.
        jitter: added to the kernel diagonal, relative to the signal variance.
        max_steps: BFGS steps for the hyperparameters.
        grid: samples per axis of the search cuboid; top_k: best samples averaged per round.
        shrink: cuboid scale factor per round; tol_m: stop when the half size is below this [m].
        margin_m: the initial cuboid is the data bounding box grown by this [m].
        stages: 1 = one GP per anchor; 2 = then refit on the `n_train` shortest ranges and search
            again
            around the first estimate (the paper's coarse-to-fine "iterative GP").
        search: `cuboid` (the paper: extremum of the GP mean by the iterative cuboid search) or
            `gradient` (eikonal step a = p - r grad r from the `top_k` training inputs with the
            smallest predicted range, `gradient_step`; the anchor may lie outside the covered
            region), keeping the option (candidates' mean, each candidate, the cuboid answer) most
            consistent with the GP's range field (`range_consistency`).
        max_spread_ratio: `mean=anchor` only: fall back to the `nls` start (and its covariance)
            for an anchor whose fitted position explains all its ranges clearly worse than the
            start: robust spread of r - |p - a| (`cone_spread`) above this many times nls's
            (0 = never; the fit diverged when f absorbed the geometry).
        max_shift_sigma: `mean=anchor` only: the anchor moves at most this many standard deviations
            (Mahalanobis, `nls` covariance) from the `nls` start (0 = unbounded).
        robust: `mean=anchor` only: heavy-tailed white noise (variance / Cauchy weight of the `nls`
            residual) so that outliers do not bend the GP.
        combine: `mean=anchor` only: `fuse` (the GP's anchor and the `nls` answer averaged with
            their precisions, then bounded) or `bound` (the GP's anchor, bounded).
        max_length, min_signal: `mean=anchor` only: soft bounds on the kernel (`gp_anchor.hyper_penalty`):
            length scale at most `max_length` times the radius of the training inputs about their
            centroid, signal variance at least `min_signal` times the variance of the `nls` residuals
            (max_length = 0: no bounds).
        bound_clusters: `mean=anchor` only: the `nls` covariance that weighs the `nls` answer in `fuse` and
            sizes `max_shift_sigma`: the cluster jackknife over this many stretches (0: the model
            covariance s^2 (J^T W J)^-1; -1: the covariance `nls` reports, over `cov_clusters` and
            `n_clusters` stretches). Either way the covariance is at least the one `nls` reports before the
            mirror check's profile (which then widens each method's about its own estimate).
        model: `mean=anchor` only: `excess` (default, below) or `subsample` (the default until the fourteenth
            round: the spatial GP on `n_train` ranges, fused with and bounded by `nls`) or `path`
            (`jaxcal.trajectory.gp_path`: every range, r = |p - a| + b + f(s) + e with f a Matern `nu` (0.5 or
            1.5) GP along the path's arc length s, by a Kalman filter; no fuse or bound, `nls` is the start and
            the fallback) or `space` (`jaxcal.trajectory.gp_space`: as `path` with f a Matern `nu` GP over the
            horizontal position, on a Hilbert-space basis); `excess` (`jaxcal.trajectory.gp_excess`): every
            range, a one-sided NLOS excess whose probability is tied to route cells; no fuse or bound. fuse,
            bound, n_train, block only apply to `subsample`.
        n_basis, basis_margin: `model=space` only: sine basis functions per horizontal axis (n_basis^2 in
            all) on the positions' box grown by the factor basis_margin (> 1); max_signal: the signal
            variance at most this times the variance of the Cauchy-weighted `nls` residuals (soft bound).
        excess_cells, excess_rounds, excess_prior, excess_max_ranges: `model=excess` only
            (`jaxcal.trajectory.gp_excess`, the one-sided NLOS excess): route cells along the longer side of each
            anchor's box, EM rounds, pseudo ranges shrinking a cell's NLOS probability to the anchor's mean, and
            the most ranges per anchor the EM runs on (evenly spaced in time; 0 = all). Checked whatever the
            model.
        block, max_ranges: `mean=anchor` only: the GP's covariance is block-diagonal over blocks
            of `block` consecutive ranges, on at most `max_ranges` ranges per anchor (evenly thinned
            in time); `block=0` (default): one dense GP on the stratified `n_train` subsample.
        estimate_offset: as for `nls` (on by default: the offset is fitted with `nls`'s anchors first).
        systematic_pool: off for `gp` (on for `nls` and `ls`): its excess model takes the NLOS excess out of the
            range model instead of letting the anchor absorb it, so each anchor's residuals show its own place errors;
            pooled over the campaign, the simulated campus family's ellipses became too wide (NEES/dof median
            0.44-0.61, coverage 97-98 %; twenty-third round).
        estimate_drift, drift_model: as for `nls` (`mean=anchor`, every model): the shared pose error nls estimates
            from the ranges at its answer, the same estimate made once, is added to gp's covariance where no
            `pose_sd_m` / `pose_drift` is stated (a statement wins); `jaxcal.trajectory.drift.drift_for_method`.
        min_ranges, planar_tol_m, planar_ratio, side, order, knot_dt_s: as for `ls`, and so are
            max_gap_s, time_offset_s, max_offset_s.
    """

    estimate_offset: bool = True
    estimate_drift: bool = True
    drift_model: str = "auto"
    systematic_pool: bool = False
    target: str = "range"
    mean: str = "anchor"
    nu: float = 1.5
    n_train: int = 300
    n_bins: int = 10
    seed: int = 0
    jitter: float = 1e-6
    max_steps: int = 200
    grid: int = 11
    top_k: int = 10
    shrink: float = 0.5
    tol_m: float = 0.005
    margin_m: float = 5.0
    stages: int = 2
    search: str = "cuboid"
    max_spread_ratio: float = 3.0
    max_shift_sigma: float = 3.0
    robust: bool = True
    combine: str = "fuse"
    max_length: float = 1.0
    min_signal: float = 1e-4
    block: int = 0
    max_ranges: int = 4096
    bound_clusters: int = 0
    model: str = "excess"
    n_basis: int = 20
    max_signal: float = 1.0
    basis_margin: float = 1.5
    excess_cells: float = 16.0
    excess_rounds: int = 8
    excess_prior: float = 5.0
    excess_max_ranges: int = 4000


def fit_hyper(x, y, mask, init: Hyper, nu: float = 1.5, jitter: float = 1e-6, max_steps: int = 200):
    """Maximise the marginal likelihood over the log hyperparameters (optx BFGS); returns Hyper.

    Args:
        x: (n, 3) [m]. y: (n,) centred targets. mask: (n,). init: starting point.
    """
    return _fit_hyper(x, y, mask, init, nu, jitter, max_steps)[0]


def _fit_hyper(x, y, mask, init: Hyper, nu: float, jitter: float, max_steps: int):
    """`fit_hyper` plus the outcome code of the BFGS fit (`jaxcal.solver.outcome`): (Hyper, code)."""

    def loss(h, _):
        # The objective is scaled by 1/n so that the BFGS tolerances mean the same for any n.
        return neg_log_marginal_likelihood(h, x, y, mask, nu, jitter) / jnp.maximum(jnp.sum(mask), 1)

    solver: optx.AbstractMinimiser = optx.BFGS(rtol=1e-6, atol=1e-6)
    sol: optx.Solution = optx.minimise(loss, solver, init, max_steps=max_steps, throw=False)
    ok = jnp.isfinite(loss(sol.value, None))
    return jax.tree.map(lambda a, b: jnp.where(ok, a, b), sol.value, init), S.outcome(sol)


class _Posterior(eqx.Module):
    x: Array
    mask: Array
    alpha: Array
    chol: Array
    hyper: Hyper
    mean: Array
    nu: float = eqx.field(static=True)


def _posterior(h, x, y, mask, mean, nu, jitter):
    k = _gram(h, x, mask, nu, jitter)
    chol = jnp.linalg.cholesky(k)
    alpha = jax.scipy.linalg.cho_solve((chol, True), jnp.where(mask, y, 0.0))
    return _Posterior(x, mask, alpha, chol, h, mean, nu)


def predict(post: _Posterior, xs: Float[Array, "m 3"], with_var: bool = False):
    """Posterior mean (and variance) of the GP target at `xs` (m, 3) [m]."""
    ks = matern(
        _sqdist(xs, post.x),
        jnp.exp(post.hyper.log_length),
        jnp.exp(post.hyper.log_variance),
        post.nu,
    )
    ks = ks * post.mask[None, :]
    mu = post.mean + ks @ post.alpha
    if not with_var:
        return mu
    v = jax.scipy.linalg.solve_triangular(post.chol, ks.T, lower=True)
    var = jnp.exp(post.hyper.log_variance) - jnp.sum(v**2, axis=0)
    return mu, jnp.maximum(var, 0.0)


# ---------------------------------------------------------------------------------------- search


def search_anchor(
    post: _Posterior,
    centre,
    half,
    target: str,
    grid: int,
    top_k: int,
    shrink: float,
    n_rounds: int,
    grid_z: int,
):
    """Iterative cuboid search for the extremum of the GP mean (one anchor).

    Args:
        post: GP posterior. centre: (3,) initial cuboid centre [m]. half: (3,) half sizes [m].
        target: `range` (minimise) or `inv-log` (maximise). grid, grid_z: samples per axis (static).
        top_k: samples averaged per round. shrink: scale per round. n_rounds: rounds (static).

    Returns:
        (estimate (3,), covariance (3, 3) of the last round's top-k samples).
    """
    ax = jnp.linspace(-1.0, 1.0, grid)
    az = jnp.linspace(-1.0, 1.0, grid_z) if grid_z > 1 else jnp.zeros(1)
    unit = jnp.stack(jnp.meshgrid(ax, ax, az, indexing="ij"), axis=-1).reshape(-1, 3)
    sign = 1.0 if target == "inv-log" else -1.0  # score to maximise

    def round_(carry, _):
        c, h = carry
        pts = c + unit * h
        score = sign * predict(post, pts)
        _, idx = jax.lax.top_k(score, top_k)
        best = pts[idx]
        new_c = jnp.mean(best, axis=0)
        d = best - new_c
        return (new_c, h * shrink), d.T @ d / max(top_k - 1, 1)

    (c, _), covs = jax.lax.scan(round_, (centre, half), None, length=n_rounds)
    return c, covs[-1]


def _range_sd(mu, var, target):
    """Posterior sd of the GP target mapped to metres (delta method for `inv-log`)."""
    if target == "range":
        return jnp.sqrt(var)
    return jnp.abs(jax.grad(lambda y: from_target(y, "inv-log"))(mu)) * jnp.sqrt(var)


def range_consistency(
    post: _Posterior,
    x: Float[Array, "n 3"],
    mask: Bool[Array, " n"],
    target: str,
    anchor: Float[Array, " 3"],
) -> Float[Array, ""]:
    """How well an anchor explains the GP's range field: median |e_i - median(e)| over the inputs,
    e_i = r(p_i) - |p_i - a| with r the posterior mean range (a constant bias costs nothing) [m].

    Args:
        post: GP posterior. x: (n, 3) training inputs [m]. mask: (n,) valid. target: GP target.
        anchor: (3,) candidate [m] (frame of `post`).
    """
    r = from_target(predict(post, x), target)
    e = jnp.where(mask, r - _cone(x, anchor), jnp.nan)
    return jnp.nanmedian(jnp.abs(e - jnp.nanmedian(e)))


def gradient_step(
    post: _Posterior,
    x: Float[Array, "n 3"],
    mask: Bool[Array, " n"],
    target: str,
    top_k: int,
    planar: Bool[Array, ""],
    side: float,
):
    """Anchor from the GP's range field at the data: a = p - r(p) grad r(p) (eikonal, one anchor).

    A range field r(p) = |p - a| has |grad r| = 1 and grad r pointing away from the anchor, so every
    point p with its range and gradient gives the anchor; the GP posterior mean supplies a denoised
    r and grad r at the training inputs, where it is supported by data (the cuboid search instead
    reads the GP where it may have to extrapolate). The `top_k` training inputs with the smallest
    predicted range each give a candidate; the estimate is their mean. Planar inputs (z not
    observable): the horizontal step uses grad_xy r (norm clipped to 1) and the height above the
    point is side * r sqrt(1 - |grad_xy r|^2); otherwise the gradient is normalised to unit length.

    Args:
        post: GP posterior. x: (n, 3) training inputs [m] (frame of `post`). mask: (n,) valid.
        target: `range` or `inv-log`. top_k: candidates averaged (static). planar: whether z is
        unobservable. side: +1 anchor above the plane of the inputs, -1 below.

    Returns:
        (estimate (3,), sample covariance (3, 3) of the candidates, the best training input (3,)).
    """
    return _gradient_candidates(post, x, mask, target, top_k, planar, side)[:3]


def _gradient_candidates(post, x, mask, target, top_k, planar, side):
    y, gy = jax.vmap(jax.value_and_grad(lambda q: predict(post, q[None])[0]))(x)
    r = from_target(y, target)
    dr = jax.vmap(jax.grad(lambda v: from_target(v, target)))(y)
    g = gy * dr[:, None]
    r_ok = mask & jnp.isfinite(r)
    k = min(top_k, x.shape[0])
    _, idx = jax.lax.top_k(jnp.where(r_ok, -r, -jnp.inf), k)
    w = r_ok[idx].astype(x.dtype)  # fewer valid inputs than k: the padding gets no weight
    p, r, g = x[idx], jnp.where(r_ok[idx], jnp.maximum(r[idx], 0.0), 0.0), g[idx]
    s2 = jnp.sum(g[:, :2] ** 2, axis=1)
    s = jnp.sqrt(jnp.where(s2 > 0, s2, 1.0))
    gxy = g[:, :2] / jnp.maximum(s, 1.0)[:, None]
    height = side * r * jnp.sqrt(jnp.maximum(1.0 - jnp.sum(gxy**2, axis=1), 0.0))
    cand_planar = jnp.concatenate([p[:, :2] - r[:, None] * gxy, (p[:, 2] + height)[:, None]], 1)
    n2 = jnp.sum(g**2, axis=1)
    unit = g / jnp.sqrt(jnp.where(n2 > 0, n2, 1.0))[:, None]
    cand = jnp.where(planar, cand_planar, p - r[:, None] * unit)
    nw = jnp.maximum(jnp.sum(w), 1.0)
    est = jnp.sum(cand * w[:, None], axis=0) / nw
    d = (cand - est) * w[:, None]
    cand = jnp.where(w[:, None] > 0, cand, jnp.nan)  # padding: never chosen downstream
    return est, d.T @ d / jnp.maximum(nw - 1.0, 1.0), p[0], cand


# ------------------------------------------------------------------------------------ subsample


# ------------------------------------------------------------------------------------ calibrate


@eqx.filter_jit
def _calibrate_all(x, r, mask, centre, half, planar, p: GPParams, n_rounds: int, grid_z: int):
    def one(x, r, m, c0, h0, pl):
        w = m.astype(x.dtype)
        n = jnp.maximum(jnp.sum(w), 1.0)
        origin = jnp.sum(x * w[:, None], axis=0) / n  # centred inputs for conditioning
        xc = (x - origin) * w[:, None]
        y = to_target(jnp.where(m, r, 1.0), p.target)
        mean = jnp.sum(y * w) / n if p.target == "range" else jnp.zeros(())
        yc = (y - mean) * w
        var_y = jnp.maximum(jnp.sum(yc**2) / n, 1e-6)
        ext = jnp.max(jnp.where(m[:, None], jnp.abs(xc), 0.0))
        init = Hyper(jnp.log(jnp.maximum(0.3 * ext, 1e-2)), jnp.log(var_y), jnp.log(0.01 * var_y))
        h, code = _fit_hyper(xc, yc, m, init, p.nu, p.jitter, p.max_steps)
        post = _posterior(h, xc, yc, m, mean, p.nu, p.jitter)
        est, cov = search_anchor(post, c0 - origin, h0, p.target, p.grid, p.top_k, p.shrink, n_rounds, grid_z)
        pt = est
        mu, var = predict(post, pt[None], with_var=True)
        d_hat = from_target(mu[0], p.target)
        sd = _range_sd(mu[0], var[0], p.target)
        # Clip to the anchor's range span: far from the data an inv-log prediction near 0 maps to
        # an enormous range.
        r_max = jnp.max(jnp.where(m, r, 0.0))
        height = jnp.clip(d_hat, 0.0, r_max)
        sd = jnp.minimum(sd, r_max)
        est = jnp.where(pl, est.at[2].set(est[2] + p.side * height), est)
        if p.search == "gradient":
            est_g, cov_g, pt_g, cands = _gradient_candidates(post, xc, m, p.target, p.top_k, pl, p.side)
            # The eikonal step is local (it trusts the GP's gradient at a few inputs); keep the
            # candidate, the cuboid answer included, most consistent with the whole range field.
            options = jnp.concatenate([est_g[None], est[None], cands])
            score = jax.vmap(lambda a: range_consistency(post, xc, m, p.target, a))(options)
            best = jnp.argmin(jnp.where(jnp.isfinite(score), score, jnp.inf))
            mu, var = predict(post, pt_g[None], with_var=True)
            sd = jnp.minimum(_range_sd(mu[0], var[0], p.target), r_max)
            est, cov = options[best], cov_g
        return est + origin, cov + sd**2 * jnp.eye(3), h, code

    # lax.map, not vmap: batched triangular solves (Cholesky gradients) are far slower on CPU than a
    # sequence of unbatched ones; the anchors are independent either way.
    return jax.lax.map(lambda a: one(*a), (x, r, mask, centre, half, planar))


@in_float64
@one_blas_thread
def calibrate(dataset, params=None, config=None, progress=None) -> Result:
    """`--method gp`: GP regression of the range per anchor, then the anchor search (frame `world`).

    Args:
        dataset: TrajectoryDataset. params: overrides of `GPParams`. config: ignored.
        progress: called with 1 after each stage (`params.stages` calls; every anchor is fitted at
            once in a stage, vmapped); one call in all with `mean=anchor`.

    Returns:
        Result with `position` (A, 3) and `covariance` (A, 3, 3); fitted hyperparameters in params.
    """
    from jaxcal.trajectory.poses import AnchorRanges

    p = with_overrides(GPParams(), params)
    if p.target not in ("range", "inv-log"):
        raise JaxcalError(f"parameter target: expected range or inv-log, got {p.target!r}")
    if p.search not in ("cuboid", "gradient"):
        raise JaxcalError(f"parameter search: expected cuboid or gradient, got {p.search!r}")
    if p.mean not in ("constant", "anchor"):
        raise JaxcalError(f"parameter mean: expected constant or anchor, got {p.mean!r}")
    if p.drift_model not in MODELS:
        raise JaxcalError(f"parameter drift_model: expected one of {', '.join(MODELS)}, got {p.drift_model!r}")
    if p.model not in ("subsample", "path", "space", "excess"):
        raise JaxcalError(f"parameter model: expected subsample, path, space or excess, got {p.model!r}")
    # checked whatever the model, so that a wrong value is not ignored silently where it does not apply
    if not (p.excess_cells > 0 and p.excess_rounds >= 1 and p.excess_prior >= 0 and p.excess_max_ranges >= 0):
        raise JaxcalError(
            "parameters excess_cells > 0, excess_rounds >= 1, excess_prior >= 0 and excess_max_ranges >= 0 required, "
            f"got {p.excess_cells}, {p.excess_rounds}, {p.excess_prior}, {p.excess_max_ranges}"
        )
    if p.model == "space" and (p.mean != "anchor" or p.n_basis < 2 or p.basis_margin <= 1.0):
        raise JaxcalError(
            f"parameter model=space needs mean=anchor, n_basis >= 2 and basis_margin > 1, got {p.mean!r}, "
            f"{p.n_basis}, {p.basis_margin}"
        )
    if p.model == "path" and (p.mean != "anchor" or p.nu not in (0.5, 1.5)):
        raise JaxcalError(f"parameter model=path needs mean=anchor and nu 0.5 or 1.5, got {p.mean!r}, {p.nu}")
    matern(jnp.zeros(1), jnp.asarray(1.0), jnp.asarray(1.0), p.nu)  # validates nu
    if p.grid < 2 or p.top_k < 1 or p.top_k > p.grid**2 or not 0.0 < p.shrink < 1.0 or p.tol_m <= 0:
        raise JaxcalError("parameters grid >= 2, 1 <= top_k <= grid^2, 0 < shrink < 1, tol_m > 0 required")
    groups, info = prepare_offset(dataset, p)
    pos = np.asarray(groups.position)
    rng_m = np.asarray(groups.range)
    mask = np.asarray(groups.mask)
    a_n = pos.shape[0]
    n = max(1, min(p.n_train, int(mask.sum(axis=1).max())))
    planar = np.array(
        [
            bool(mask[a].any())
            and bool(
                is_planar(
                    pos[a, mask[a], 2].std(),
                    np.linalg.norm(pos[a, mask[a], :2].std(axis=0)),
                    p.planar_tol_m,
                    p.planar_ratio,
                )
            )
            for a in range(a_n)
        ]
    )
    if p.mean == "anchor":
        from jaxcal.trajectory.gp_anchor import calibrate_anchor_mean
        from jaxcal.trajectory.gp_excess import calibrate_excess
        from jaxcal.trajectory.gp_path import calibrate_path
        from jaxcal.trajectory.gp_space import calibrate_space

        if p.model == "path":
            out = calibrate_path(dataset, p, groups, info, planar)
        elif p.model == "space":
            out = calibrate_space(dataset, p, groups, info, planar)
        elif p.model == "excess":
            out = calibrate_excess(dataset, p, groups, info, planar)
        else:
            out = calibrate_anchor_mean(dataset, p, groups, info, n, planar)
        if progress is not None:
            progress(1)
        return out
    grid_z = 1 if planar.all() else p.grid
    est: Any = None
    cov: Any = None
    hyp: Any = None
    half_prev = np.full((a_n, 3), np.inf)
    for stage in range(p.stages):
        x = np.zeros((a_n, n, 3))
        r = np.zeros((a_n, n))
        m = np.zeros((a_n, n), dtype=bool)
        centre = np.zeros((a_n, 3))
        half = np.ones((a_n, 3))
        for a in range(a_n):
            valid = np.nonzero(mask[a])[0]
            if valid.size == 0:
                continue
            if stage == 0:  # stratified over the whole range span, cuboid = data box + margin
                sel = valid[stratified_subsample(rng_m[a, valid], n, p.n_bins, p.seed + a)]
                lo, hi = pos[a, valid].min(axis=0), pos[a, valid].max(axis=0)
                centre[a] = 0.5 * (lo + hi)
                half[a] = 0.5 * (hi - lo) + p.margin_m
            else:  # local refit: the n shortest ranges, cuboid around the last estimate
                sel = valid[np.argsort(rng_m[a, valid], kind="stable")[:n]]
                prev = np.asarray(est[a])
                centre[a] = np.where(np.isfinite(prev), prev, pos[a, sel].mean(axis=0))
                half[a] = min(rng_m[a, sel].max(), float(half_prev[a].max())) + p.tol_m
            x[a, : sel.size], r[a, : sel.size], m[a, : sel.size] = pos[a, sel], rng_m[a, sel], True
            if planar[a]:
                centre[a, 2] = pos[a, valid, 2].mean()
                half[a, 2] = 0.0
        half_prev = half
        if stage == 0:  # the same (static) number of rounds in every stage: one compilation
            n_rounds = max(1, int(math.ceil(math.log(half.max() / p.tol_m) / math.log(1.0 / p.shrink))))
        args = tuple(jnp.asarray(a) for a in (x, r, m, centre, half, planar))

        def stage_fit(k: int, args=args, n_rounds=n_rounds):
            return _fit_stage(args, eqx.tree_at(lambda q: q.max_steps, p, k), n_rounds, grid_z)

        (est, cov, hyp, codes), codes, steps = S.retry_unconverged(stage_fit, p.max_steps)
        if progress is not None:
            jax.block_until_ready(est)
            progress(1)
    info = dict(
        info,
        n_rounds=n_rounds,
        planar=planar.tolist(),
        length_m=np.exp(np.asarray(hyp.log_length)).tolist(),
        signal_var=np.exp(np.asarray(hyp.log_variance)).tolist(),
        noise_var=np.exp(np.asarray(hyp.log_noise)).tolist(),
    )
    kept = AnchorRanges(groups.position, groups.range, groups.mask)
    hint = f"raise max_steps (now {p.max_steps}; retried with {steps}) of the hyperparameter fit"
    return finish(dataset, "gp", p, kept, est, cov, info, report_fits("gp", codes, groups, p, hint))


def _fit_stage(args, p: GPParams, n_rounds: int, grid_z: int):
    """One stage of `_calibrate_all` for `jaxcal.solver.retry_unconverged`: (output, outcome codes)."""
    x, r, mask, centre, half, planar = args
    out = _calibrate_all(x, r, mask, centre, half, planar, p, n_rounds, grid_z)
    return out, out[3]
