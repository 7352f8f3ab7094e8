"""The GP with the anchor as a mean parameter (`gp` with `mean=anchor`, the default), seeded and
bounded by `nls`.

Model per anchor: r_i = |p_i - a| + b + f(p_i) + e_i, f ~ GP(0, Matern) a spatially correlated range
error (NLOS bias along stretches of the route, pose drift), e_i white noise with a heavy tail. The
anchor a, the bias b and the kernel hyperparameters maximise the marginal likelihood
(`fit_mean_model`, Optimistix BFGS).

Training set: by default (`block=0`) one dense GP on a stratified subsample of `n_train` (300)
ranges per anchor (`gp.stratified_subsample`); `nls` has used every range for the seed. With
`block=m > 0` every range counts instead (at most `max_ranges` per anchor, evenly thinned in time):
the ranges, in time order, are cut into blocks of m consecutive ranges, independent of each other
(`blocks_nlml`), a block-diagonal covariance at O(n m^2) instead of O(n^3); f then models errors
that persist along a stretch of the route without coupling distant revisits. Not the default:
measured slower on this CPU (the sequential loop over blocks inside BFGS) and no more accurate.

1. Seed: `nls` (robust Cauchy IRLS over *all* ranges) gives a0, b0, its covariance C0 and residuals.
2. Heavy tail: the white noise of range i has variance s_n^2 / w_i with w_i the Cauchy weight of its
   `nls` residual, 1 / (1 + (e_i / c)^2), c = 2.385 x 1.4826 x MAD (the `nls` scale): one IRLS step
   of a Cauchy (Student-t, 1 dof) likelihood, so an outlier does not bend f (`robust=False`: w = 1).
3. Fuse and bound: the GP's anchor and the `nls` answer are averaged with their precisions, and the GP
   may move the anchor only within `max_shift_sigma` standard deviations of the `nls` fit; beyond, the
   step is shortened to that boundary. Both use `nls`'s model covariance s^2 (J^T W J)^-1
   (`bound_clusters=0`), like with like: the GP's is the curvature of its marginal likelihood, which
   counts its ranges as independent given f. Sized by the wider cluster jackknife that `nls` reports
   (C0), the GP's answer from 300 ranges outweighed `nls`'s from all of them where f finds nothing to
   explain: hanyang LOS 1.32x `nls` (jackknife over 4 and 16 stretches), 1.25x (16), 1.21x (32),
   1.13x (64), 0.98x (model; the development file of that choice, with even seeds of the simulated
   family, where 0 and 64 tied). A smooth f
   can trade off against the geometry of a far or barely observed anchor (its cone is almost a
   plane) and carry it metres away; the bound makes the GP a correction of `nls`, never a
   replacement. An anchor whose fitted position explains all its ranges clearly worse than the
   start (`cone_spread` above `max_spread_ratio` x nls's) falls back to `nls` (`info_fallback_nls`).
4. Covariance: the anchor block of the inverse Hessian of the negative log marginal likelihood,
   widened in every direction to C0 (the cluster-robust `nls` covariance) and by d d^T, d the step
   from the `nls` answer: the two estimates disagreeing by d means neither is known better than
   that. Directions the data cannot fix (the height from a flat route) keep the large variance and
   `finish` leaves such a height NaN.
5. Shared pose error: where none is stated and `estimate_drift` is on (the default, as for `nls`), the one `nls`
   estimates from the ranges at its answer (`jaxcal.trajectory.drift.drift_for_method`: the same estimate, made
   once) is added, the part nls's stretch jackknife holds left out as for nls; the covariance floor of step 4 is
   nls's covariance without it, so gp's ellipses were smaller than nls's on drifting poses (fourteenth round).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from jaxcal import solver as S
from jaxcal.data import Result
from jaxcal.params import with_overrides
from jaxcal.trajectory.common import cauchy_weights, finish, report_fits, widen_covariance
from jaxcal.trajectory.drift import drift_for_method
from jaxcal.trajectory.gp_kernel import (
    Hyper,
    _cone,
    hyper_penalty,
    laplace_fit,
    neg_log_marginal_likelihood,
    stratified_subsample,
    to_target,
)

__all__ = [
    "MeanModel",
    "mean_model_nlml",
    "blocks_nlml",
    "fit_mean_model",
    "cone_spread",
    "cauchy_weights",
    "bound_step",
    "hyper_penalty",
    "widen_covariance",
    "fuse",
    "calibrate_anchor_mean",
]


class MeanModel(eqx.Module):
    """GP with the range model as its mean: y(p) = T(|p - a| + b) + f(p), f ~ GP(0, Matern + noise).

    Attributes:
        anchor: (3,) anchor position a [m] (in the frame of the inputs). bias: range bias b [m].
        hyper: kernel and noise hyperparameters (log space).
    """

    anchor: Float[Array, ...]
    bias: Float[Array, ...]
    hyper: Hyper


def mean_model_nlml(
    theta: MeanModel,
    x: Float[Array, "n 3"],
    r: Float[Array, " n"],
    mask: Bool[Array, " n"],
    nu: float = 1.5,
    jitter: float = 1e-6,
    target: str = "range",
    noise_scale: Float[Array, " n"] | None = None,
) -> Float[Array, ""]:
    """-log p(r | x, theta) of the GP with the parametric mean T(|p - a| + b) (T = `to_target`).

    Args:
        theta: mean parameters and hyperparameters. x: (n, 3) tag positions [m]. r: (n,) ranges [m].
        mask: (n,) valid entries. nu: Matern smoothness (static). jitter: relative diagonal jitter.
        target: `range` or `inv-log` (the GP models T(r)).
        noise_scale: (n,) white-noise variance multipliers (1 / Cauchy weight); None: 1.
    """
    m = to_target(_cone(x, theta.anchor) + theta.bias, target)
    y = jnp.where(mask, to_target(jnp.where(mask, r, 1.0), target) - m, 0.0)
    return neg_log_marginal_likelihood(theta.hyper, x, y, mask, nu, jitter, noise_scale)


def blocks_nlml(
    theta: MeanModel,
    x: Float[Array, "blocks m 3"],
    r: Float[Array, "blocks m"],
    mask: Bool[Array, "blocks m"],
    nu: float = 1.5,
    jitter: float = 1e-6,
    target: str = "range",
    noise_scale: Float[Array, "blocks m"] | None = None,
) -> Float[Array, ""]:
    """Sum of `mean_model_nlml` over blocks of consecutive ranges (independent across blocks, one
    set of parameters): a block-diagonal covariance, O(n m^2) for n ranges in blocks of m.

    Args:
        theta: parameters. x, r, mask, noise_scale: as for `mean_model_nlml` with a leading block
            axis (an all-masked block adds 0).
    """
    s = jnp.ones_like(r) if noise_scale is None else noise_scale
    # lax.map, not vmap: a vmapped (batched) Cholesky inside the BFGS loop hung XLA on CPU for more
    # than 8 blocks (no CPU used, never returned), and unbatched ones are faster there anyway.
    per = jax.lax.map(
        lambda a: mean_model_nlml(theta, a[0], a[1], a[2], nu, jitter, target, a[3]),
        (x, r, mask, s),
    )
    return jnp.sum(per)


def fit_mean_model(
    x,
    r,
    mask,
    init: MeanModel,
    nu=1.5,
    jitter=1e-6,
    max_steps=200,
    target="range",
    noise_scale=None,
):
    """Maximise the marginal likelihood over anchor, bias and log hyperparameters (optx BFGS).

    Args:
        x: (n, 3) or (blocks, m, 3) [m]; r, mask, noise_scale: (n,) or (blocks, m) (`blocks_nlml`).

    Returns:
        (fitted MeanModel, covariance (3, 3) of the anchor from the inverse Hessian of the NLML).
    """
    return _fit_mean_model(x, r, mask, init, nu, jitter, max_steps, target, noise_scale)[:2]


def _fit_mean_model(x, r, mask, init: MeanModel, nu, jitter, max_steps, target, noise_scale, bounds=None):
    """`fit_mean_model` plus the outcome code of the BFGS fit (`jaxcal.solver.outcome`); `bounds`:
    (log_max_length, log_min_variance) of `hyper_penalty` (None: none)."""
    n = jnp.maximum(jnp.sum(mask), 1)

    def nlml(th):
        if x.ndim == 3:
            out = blocks_nlml(th, x, r, mask, nu, jitter, target, noise_scale)
        else:
            out = mean_model_nlml(th, x, r, mask, nu, jitter, target, noise_scale)
        return out if bounds is None else out + hyper_penalty(th.hyper, *bounds)

    return laplace_fit(nlml, init, n, max_steps)


@eqx.filter_jit
def _fit_blocks(x, r, mask, noise_scale, init_anchor, init_bias, p):
    """All anchors (lax.map): x (A, B, m, 3), r / mask / noise_scale (A, B, m); see module doc."""

    def one(x, r, m, s, a0, b0):
        w = m.astype(x.dtype)
        n = jnp.maximum(jnp.sum(w), 1.0)
        origin = jnp.sum(x * w[..., None], axis=(0, 1)) / n  # centred inputs for conditioning
        xc = (x - origin) * w[..., None]
        a0 = a0 - origin
        y = to_target(jnp.where(m, r, 1.0), p.target)
        res = jnp.where(m, y - to_target(_cone(xc, a0) + b0, p.target), 0.0)
        var_y = jnp.maximum(jnp.sum(res**2 / s) / n, 1e-6)
        # initial length scale: the median extent of a block (the stretch one block covers)
        nb = jnp.maximum(jnp.sum(w, axis=1), 1.0)
        cb = jnp.sum(xc * w[..., None], axis=1) / nb[:, None]
        ext_b = jnp.max(jnp.where(m, jnp.linalg.norm(xc - cb[:, None], axis=-1), 0.0), axis=1)
        span = jnp.nanmedian(jnp.where(jnp.any(m, axis=1), ext_b, jnp.nan))
        init = MeanModel(
            a0,
            b0,
            Hyper(jnp.log(jnp.clip(span, 0.1, 1e3)), jnp.log(0.5 * var_y), jnp.log(0.5 * var_y)),
        )
        radius = jnp.max(jnp.where(m, jnp.linalg.norm(xc, axis=-1), 0.0))
        bounds = None
        if p.max_length > 0:
            bounds = (jnp.log(jnp.maximum(p.max_length * radius, 1e-2)), jnp.log(p.min_signal * var_y))
        th, cov, code = _fit_mean_model(xc, r, m, init, p.nu, p.jitter, p.max_steps, p.target, s, bounds)
        return th.anchor + origin, cov, th.hyper, th.bias, code

    # lax.map, not vmap: batched Cholesky gradients are slow on CPU; anchors are independent.
    return jax.lax.map(lambda a: one(*a), (x, r, mask, noise_scale, init_anchor, init_bias))


def cone_spread(pos, rng_m, mask, anchor) -> np.ndarray:
    """Robust spread of the range residuals e = r - |p - a| per anchor, median |e - median(e)| [m]
    (a constant range bias costs nothing); NaN for an anchor without ranges or estimate.

    Args:
        pos: (A, n, 3) tag positions [m]. rng_m: (A, n) ranges [m]. mask: (A, n) valid.
        anchor: (A, 3) anchor positions [m].
    """
    pos, rng_m, mask, anchor = map(np.asarray, (pos, rng_m, mask, anchor))
    out = np.full(pos.shape[0], np.nan)
    for a in range(pos.shape[0]):
        if mask[a].any() and np.isfinite(anchor[a]).all():
            e = rng_m[a, mask[a]] - np.linalg.norm(pos[a, mask[a]] - anchor[a], axis=1)
            out[a] = np.median(np.abs(e - np.median(e)))
    return out


def bound_step(a0: np.ndarray, cov0: np.ndarray, a: np.ndarray, max_sigma: float) -> np.ndarray:
    """`a` moved towards `a0` until its Mahalanobis distance under `cov0` is at most `max_sigma`.

    Args:
        a0: (3,) start [m]. cov0: (3, 3) its covariance [m^2] (pseudo-inverse: a singular direction
            is unbounded). a: (3,) proposed estimate [m]. max_sigma: bound (<= 0: no bound).

    Returns:
        (3,) a0 + d min(1, max_sigma / |d|_C0), d = a - a0.
    """
    d = np.asarray(a, float) - np.asarray(a0, float)
    if max_sigma <= 0 or not np.isfinite(d).all() or not np.isfinite(cov0).all():
        return np.asarray(a, float)
    m = float(np.sqrt(max(d @ np.linalg.pinv(cov0) @ d, 0.0)))
    return np.asarray(a0, float) + d * min(1.0, max_sigma / m if m > 0 else 1.0)


def fuse(a0: np.ndarray, cov0: np.ndarray, a1: np.ndarray, cov1: np.ndarray) -> np.ndarray:
    """Precision-weighted mean of two estimates (3,) with covariances (3, 3) (pseudo-inverses)."""
    p0, p1 = np.linalg.pinv(cov0), np.linalg.pinv(cov1)
    return np.linalg.pinv(p0 + p1) @ (p0 @ a0 + p1 @ a1)


def calibrate_anchor_mean(dataset, p, groups, info, n: int, planar) -> Result:
    """`gp` with `mean=anchor` (see module doc): `nls` start, mean-model GP, bound, covariance."""
    from jaxcal.trajectory import nls
    from jaxcal.trajectory.poses import AnchorRanges

    shared = {k: getattr(p, k) for k in ("min_ranges", "planar_tol_m", "planar_ratio", "side")}
    p_nls = with_overrides(nls.NLSParams(), shared)
    (a0, cov0, b0, _), nls_codes, _ = nls.solve_all_checked(groups, p_nls)
    pos = np.asarray(groups.position)
    rng_m = np.asarray(groups.range)
    mask = np.asarray(groups.mask)
    a_n = pos.shape[0]
    a0 = np.array(a0, dtype=float)
    b0 = np.array(b0, dtype=float)
    cov0 = np.array(cov0, dtype=float)
    # nls's reported covariance, route cells included (`nls.cell_covariances`): the floor gp reports
    cov0 = nls.cell_covariances(groups, a0, b0, cov0, p_nls)
    a_nls, b_nls = a0.copy(), b0.copy()  # nls's answer, where the shared pose error is estimated (step 5)
    # the covariance that sizes the step (fuse, bound): see `bound_clusters`; cov0 stays the reported floor
    cov_b = cov0
    if p.bound_clusters >= 0:
        x4 = jnp.asarray(np.c_[np.nan_to_num(a0), np.nan_to_num(b0)])
        clusters = (p.bound_clusters,) if p.bound_clusters > 0 else ()
        cov_b = np.array(nls.covariances_at(groups.position, groups.range, groups.mask, x4, p_nls, clusters))
        cov_b = np.where(np.isfinite(cov0), cov_b, np.nan)
    seeded = np.isfinite(a0).all(axis=1) & np.isfinite(cov0).all(axis=(1, 2))
    sels = []
    for a in range(a_n):
        valid = np.nonzero(mask[a])[0]
        if p.block <= 0:  # one dense GP on a stratified subsample of n_train ranges
            sel = valid[stratified_subsample(rng_m[a, valid], n, p.n_bins, p.seed + a)]
        elif valid.size > p.max_ranges:  # evenly thinned in time: stretches keep their structure
            sel = valid[np.round(np.linspace(0, valid.size - 1, p.max_ranges)).astype(int)]
        else:
            sel = valid
        sels.append(sel)
    m_blk = n if p.block <= 0 else p.block
    n_blk = max(1, max(-(-sel.size // m_blk) for sel in sels))
    x = np.zeros((a_n, n_blk * m_blk, 3))
    r = np.ones((a_n, n_blk * m_blk))
    m = np.zeros((a_n, n_blk * m_blk), dtype=bool)
    s = np.ones((a_n, n_blk * m_blk))
    for a, sel in enumerate(sels):
        if sel.size == 0:
            continue
        x[a, : sel.size], r[a, : sel.size], m[a, : sel.size] = pos[a, sel], rng_m[a, sel], True
        if not seeded[a]:
            a0[a] = pos[a, sel].mean(axis=0)
            b0[a] = 0.0
        elif p.robust:
            valid = np.nonzero(mask[a])[0]
            e = rng_m[a, valid] - np.linalg.norm(pos[a, valid] - a0[a], axis=1) - b0[a]
            w = cauchy_weights(e)[np.searchsorted(valid, sel)]
            s[a, : sel.size] = 1.0 / np.maximum(w, 1e-6)
    shape = (a_n, n_blk, m_blk)
    args = tuple(
        jnp.asarray(a) for a in (x.reshape(*shape, 3), r.reshape(shape), m.reshape(shape), s.reshape(shape), a0, b0)
    )

    # the pose error settings enter only the covariance (step 5): the fit runs with their defaults, so a change
    # of them reuses its compiled program (`p` is static there)
    fit_p = eqx.tree_at(lambda q: (q.estimate_drift, q.drift_model), p, (True, "auto"))

    def fit(steps):
        out = _fit_blocks(*args, eqx.tree_at(lambda q: q.max_steps, fit_p, steps))
        return out, out[4]

    (est, cov, hyp, bias, _), codes, steps = S.retry_unconverged(fit, p.max_steps)
    est, cov, bias = np.array(est), np.array(cov), np.array(bias)
    spread_gp = cone_spread(pos, rng_m, mask, est)
    spread_nls = cone_spread(pos, rng_m, mask, a0)
    # Guard (module doc, step 3): f absorbed the geometry; the anchor no longer explains its ranges.
    fallback = seeded & (
        ~np.isfinite(est).all(axis=1) | ((p.max_spread_ratio > 0) & (spread_gp > p.max_spread_ratio * spread_nls))
    )
    bounded = np.zeros(a_n, dtype=bool)
    for a in range(a_n):
        if fallback[a]:
            est[a], cov[a], bias[a] = a0[a], cov0[a], b0[a]
            continue
        if not seeded[a]:
            continue
        if p.combine == "fuse":
            est[a] = fuse(a0[a], cov_b[a], est[a], cov[a])
        if planar[a]:  # a flat path does not observe the height: the GP does not move it either
            est[a, 2] = a0[a, 2]
        proposed = est[a].copy()
        est[a] = bound_step(a0[a], cov_b[a], est[a], p.max_shift_sigma)
        bounded[a] = not np.allclose(est[a], proposed)  # the bound shortened the step (fused or not)
        d = est[a] - a0[a]
        cov[a] = widen_covariance(cov[a], cov0[a] + np.outer(d, d))
    drift_info, pose_cov = drift_for_method(dataset, groups, a_nls, b_nls, cov, p, p_nls, "gp")
    info = dict(
        info,
        **drift_info,
        fallback_nls=fallback.tolist(),
        bounded=bounded.tolist(),
        cone_spread_m=spread_gp.tolist(),
        nls_cone_spread_m=spread_nls.tolist(),
        planar=np.asarray(planar).tolist(),
        gp_ranges=[int(sel.size) for sel in sels],
        gp_blocks=n_blk,
        bias_m=np.asarray(bias).tolist(),
        length_m=np.exp(np.asarray(hyp.log_length)).tolist(),
        signal_var=np.exp(np.asarray(hyp.log_variance)).tolist(),
        noise_var=np.exp(np.asarray(hyp.log_noise)).tolist(),
    )
    kept = AnchorRanges(groups.position, groups.range, groups.mask)
    # an anchor's answer rests on both fits: the nls seed (and fallback) and the mean-model GP
    codes = np.maximum(np.asarray(codes), np.asarray(nls_codes))
    hint = f"raise max_steps (now {p.max_steps}; retried with {steps}) of the mean-model fit"
    return finish(dataset, "gp", p, kept, est, cov, info, report_fits("gp", codes, kept, p, hint), pose_cov)
