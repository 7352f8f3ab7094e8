"""The GP as the noise model of every range, along the path (`gp` with `model=path`).

Model per anchor, every range in time order:

    r_t = |p_t - a| + b + f(s_t) + e_t,

s_t the arc length of the tag's path up to range t [m], f ~ GP(0, Matern nu = 1/2 or 3/2) along s (an
NLOS state that persists while the platform passes a wall, pose drift that grows with the distance
driven: errors that are correlated along the path), e_t white noise of variance s_n^2 / w_t with w_t the
Cauchy weight of the `nls` residual (heavy tail: one IRLS step of a Cauchy likelihood). The anchor a, the
bias b and the hyperparameters (l, s_f^2, s_n^2) maximise the marginal likelihood: generalised least
squares for (a, b) with a fitted correlated-noise covariance, so correlated ranges count as fewer
(`fit_path_all`, Optimistix BFGS, seeded at `nls`).

On one input axis a Matern-1/2 or 3/2 GP is a linear state-space model (state f, or (f, f')), and the
marginal likelihood is the Kalman filter's prediction-error decomposition (`kalman_nlml`): O(n) time and
memory, so every range is used (1e5 ranges over 10 anchors). The filter is a `lax.scan`, vmapped over
anchors, hand-written rather than tinygp's quasiseparable solver: it is 40 lines, needs per-range noise
and padding masks, and the project then needs no new dependency; its test compares it with the dense
Matern covariance and a SciPy Cholesky.

Covariance of an anchor: the anchor block of the inverse Hessian of the negative log marginal likelihood
(hyperparameters included): generalised least squares counts ranges whose errors are correlated along the
path as fewer. It is then widened, in every direction where it is smaller, to the covariance `nls` reports
(its cluster jackknife): where f finds no correlation it can model (cuhksz: the length-scale bound leaves f
negligible) the GLS covariance counts 39000 ranges per anchor as independent (NEES/dof 1958 unwidened).
The price, on the development seeds (even, simulated `small`): the wider covariance moved `finish`'s
mirror-image decisions and made two of ten campaigns worse (0.68 -> 1.07 and 1.06 -> 1.52 x `nls`).
A direction the path does not observe (the height from a flat route) keeps a huge variance and `finish` leaves it NaN;
on a flat path the height is `nls`'s, as for `model=subsample`.

Fallback (a sanity check, no fuse, no bound): an anchor whose fitted position explains its ranges clearly
worse than `nls`'s (`cone_spread` above `max_spread_ratio` x nls's) or whose fit is not finite keeps the
`nls` answer and covariance (`info_fallback_nls`; one warning line when taken).

The driver (`nls` start and weights, fallback, flat-path height, covariance floor, the shared pose error nls
estimates (`estimate_drift`, `jaxcal.trajectory.drift.drift_for_method`), report) is `calibrate_every_range`,
shared with `model=space` (`gp_space`) and `model=excess` (`gp_excess`).

Revisits: s is the distance along the path, so a place passed twice at different s is two independent
pieces of f (a spatial kernel would couple them); measured on hymn's 48 survey points in
docs/benchmarks/trajectory.md.
"""

from __future__ import annotations

import logging

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from jaxcal import solver as S
from jaxcal.data import Result
from jaxcal.errors import JaxcalError
from jaxcal.params import with_overrides
from jaxcal.trajectory.common import finish, report_fits, widen_covariance
from jaxcal.trajectory.drift import drift_for_method
from jaxcal.trajectory.gp_kernel import Hyper, _cone, hyper_penalty, laplace_fit

__all__ = ["arc_length", "kalman_nlml", "path_nlml", "fit_path_all", "calibrate_path", "calibrate_every_range"]

log = logging.getLogger(__name__)


def arc_length(pos: Float[Array, "n 3"], mask: Bool[Array, " n"]) -> Float[Array, " n"]:
    """Distance travelled along the path up to each entry [m] (entries in time order; padding repeats the
    last valid value, so it adds a zero step)."""
    step = jnp.linalg.norm(jnp.diff(pos, axis=0), axis=1)
    ok = mask[1:] & mask[:-1]
    return jnp.concatenate([jnp.zeros(1, pos.dtype), jnp.cumsum(jnp.where(ok, step, 0.0))])


def _transition(dt, lam, var, nu: float):
    """Matern state-space transition A(dt) and process noise Q = P_inf - A P_inf A^T (lam = sqrt(2 nu) / l)."""
    e = jnp.exp(-lam * dt)
    if nu == 0.5:
        a = e[None, None]
        p_inf = var * jnp.ones((1, 1))
    else:
        a = e * jnp.array([[1.0 + lam * dt, dt], [-(lam**2) * dt, 1.0 - lam * dt]])
        p_inf = jnp.diag(jnp.stack([var, lam**2 * var]))
    return a, p_inf - a @ p_inf @ a.T, p_inf


def kalman_nlml(
    h: Hyper,
    s: Float[Array, " n"],
    y: Float[Array, " n"],
    mask: Bool[Array, " n"],
    nu: float = 1.5,
    noise_scale: Float[Array, " n"] | None = None,
) -> Float[Array, ""]:
    """-log p(y): zero-mean Matern GP on the sorted 1-D inputs `s` plus white noise, by the Kalman filter.

    Args:
        h: log length scale [log m], log signal variance, log noise variance. s: (n,) non-decreasing
            inputs [m]. y: (n,) targets. mask: (n,) valid entries (padding skipped). nu: 0.5 or 1.5 (static).
        noise_scale: (n,) white-noise variance multipliers (None: 1).
    """
    if nu not in (0.5, 1.5):
        raise JaxcalError(f"parameter nu: model=path needs nu 0.5 or 1.5, got {nu}")
    lam = jnp.sqrt(2.0 * nu) / jnp.exp(h.log_length)
    var = jnp.exp(h.log_variance)
    rv = jnp.exp(h.log_noise) * (jnp.ones_like(y) if noise_scale is None else noise_scale)
    dt = jnp.maximum(jnp.diff(s, prepend=s[:1]), 0.0)
    _, _, p_inf = _transition(jnp.zeros(()), lam, var, nu)
    k = p_inf.shape[0]

    def step(carry, inp):
        m, p = carry
        d, yt, ok, r = inp
        a, q, _ = _transition(d, lam, var, nu)
        m, p = a @ m, a @ p @ a.T + q
        sv = p[0, 0] + r
        v = yt - m[0]
        g = p[:, 0] / sv
        m_new, p_new = m + g * v, p - jnp.outer(g, g) * sv
        p_new = 0.5 * (p_new + p_new.T)
        term = 0.5 * (v * v / sv + jnp.log(sv) + jnp.log(2.0 * jnp.pi))
        return (jnp.where(ok, m_new, m), jnp.where(ok, p_new, p)), jnp.where(ok, term, 0.0)

    _, terms = jax.lax.scan(step, (jnp.zeros(k, y.dtype), p_inf), (dt, y, mask, rv))
    return jnp.sum(terms)


class PathModel(eqx.Module):
    """Anchor (3,) [m], range bias [m] and the path kernel's log hyperparameters."""

    anchor: Float[Array, ...]
    bias: Float[Array, ...]
    hyper: Hyper


def path_nlml(theta: PathModel, x, s, r, mask, nu: float = 1.5, noise_scale=None) -> Float[Array, ""]:
    """-log p(r | theta) of r_t = |x_t - a| + b + f(s_t) + e_t (module doc); x (n, 3), s / r / mask (n,)."""
    y = jnp.where(mask, r - _cone(x, theta.anchor) - theta.bias, 0.0)
    return kalman_nlml(theta.hyper, s, y, mask, nu, noise_scale)


@eqx.filter_jit
def fit_path_all(x, r, mask, noise_scale, a0, b0, nu: float, max_steps: int, min_signal: float, max_length: float):
    """Every anchor (vmap): x (A, n, 3), r / mask / noise_scale (A, n), seeds a0 (A, 3), b0 (A,).

    Returns:
        (anchor (A, 3), covariance (A, 3, 3), bias (A,), hyperparameters, outcome codes (A,)).
    """

    def one(x, r, m, w, a0, b0):
        nv = jnp.maximum(jnp.sum(m), 1)
        origin = jnp.sum(jnp.where(m[:, None], x, 0.0), axis=0) / nv  # centred for conditioning
        xc = jnp.where(m[:, None], x - origin, 0.0)
        s = arc_length(xc, m)
        total = jnp.maximum(s[-1], 1e-2)
        res = jnp.where(m, r - _cone(xc, a0 - origin) - b0, 0.0)
        var = jnp.maximum(jnp.sum(res**2 / w) / nv, 1e-6)
        init = PathModel(a0 - origin, b0, Hyper(jnp.log(0.05 * total), jnp.log(0.5 * var), jnp.log(0.5 * var)))
        # l at most max_length x the radius of the positions: a longer f is a slow trend over the whole
        # path that trades with the anchor's cone (cuhksz: l = 160-270 m of arc length, anchors 0.3-0.7 m off)
        radius = jnp.max(jnp.where(m, jnp.linalg.norm(xc, axis=-1), 0.0))
        bounds = (jnp.log(jnp.clip(max_length * radius, 1e-2, total)), jnp.log(min_signal * var))

        def nlml(th):
            # the penalty per range: the likelihood of 1e4-1e5 ranges would overrule a fixed one
            return path_nlml(th, xc, s, r, m, nu, w) + nv * hyper_penalty(th.hyper, *bounds)

        th, cov, code = laplace_fit(nlml, init, nv, max_steps)
        return th.anchor + origin, cov, th.bias, th.hyper, code

    return jax.vmap(one)(x, r, mask, noise_scale, a0, b0)


def calibrate_path(dataset, p, groups, info, planar) -> Result:
    """`gp` with `model=path` (module doc): `nls` start and Cauchy weights, the path GP on every range."""

    def fit(args, steps):
        return fit_path_all(*args, p.nu, steps, p.min_signal, p.max_length)

    return calibrate_every_range(dataset, p, groups, info, planar, "path", fit)


def calibrate_every_range(
    dataset, p, groups, info, planar, model: str, fit, names=("length_m", "signal_var", "noise_var")
) -> Result:
    """The driver of the GP models on every range (`model=path`, `model=space`): `nls` start and Cauchy
    weights, `fit(args, steps)` on (positions, ranges, mask, noise scales, start anchors, start biases) of
    every anchor returning (anchor (A, 3), covariance (A, 3, 3), bias (A,), Hyper, outcome codes (A,)),
    then the fallback to `nls`, the height on a flat path and the `nls` covariance floor (module doc). `names`: the
    info keys of exp(Hyper's three fields) (`model=excess` reports other quantities in them)."""
    from jaxcal.trajectory import nls
    from jaxcal.trajectory.gp_anchor import cauchy_weights, cone_spread
    from jaxcal.trajectory.poses import AnchorRanges

    shared = {k: getattr(p, k) for k in ("min_ranges", "planar_tol_m", "planar_ratio", "side")}
    p_nls = with_overrides(nls.NLSParams(), shared)
    (a0, cov0, b0, _), nls_codes, _ = nls.solve_all_checked(groups, p_nls)
    pos, rng_m, mask = (np.asarray(v) for v in (groups.position, groups.range, groups.mask))
    a0, b0, cov0 = (np.array(v, dtype=float) for v in (a0, b0, cov0))
    cov0 = nls.cell_covariances(groups, a0, b0, cov0, p_nls)  # nls's reported covariance, route cells included
    seeded = np.isfinite(a0).all(axis=1) & np.isfinite(cov0).all(axis=(1, 2))
    w = np.ones_like(rng_m)
    init_a, init_b = a0.copy(), b0.copy()
    for a in range(pos.shape[0]):
        valid = mask[a]
        if not seeded[a]:
            init_a[a] = pos[a, valid].mean(axis=0) if valid.any() else 0.0
            init_b[a] = 0.0
        elif p.robust:
            e = rng_m[a, valid] - np.linalg.norm(pos[a, valid] - a0[a], axis=1) - b0[a]
            w[a, valid] = 1.0 / np.maximum(cauchy_weights(e), 1e-6)
    args = tuple(jnp.asarray(v) for v in (pos, rng_m, mask, w, init_a, init_b))

    def fit_steps(steps):
        out = fit(args, steps)
        return out, out[4]

    (est, cov, bias, hyp, _), codes, steps = S.retry_unconverged(fit_steps, p.max_steps)
    est, cov, bias = np.array(est), np.array(cov), np.array(bias)
    spread_gp = cone_spread(pos, rng_m, mask, est)
    spread_nls = cone_spread(pos, rng_m, mask, a0)
    bad = ~np.isfinite(est).all(axis=1) | ~np.isfinite(cov).all(axis=(1, 2))
    fallback = seeded & (bad | ((p.max_spread_ratio > 0) & (spread_gp > p.max_spread_ratio * spread_nls)))
    for k in np.flatnonzero(fallback):
        est[k], cov[k], bias[k] = a0[k], cov0[k], b0[k]
    if fallback.any():
        log.warning("gp: %d anchor(s) kept the nls answer (%s GP fit worse than nls's)", int(fallback.sum()), model)
    for k in np.flatnonzero(seeded & ~fallback):
        if planar[k]:  # a flat path does not observe the height: the GP does not move it either
            est[k, 2] = a0[k, 2]
        cov[k] = widen_covariance(cov[k], cov0[k])
    # the shared pose error nls would add, estimated once at nls's answer (`drift.drift_for_method`)
    drift_info, pose_cov = drift_for_method(dataset, groups, a0, b0, cov, p, p_nls, "gp")
    info = dict(
        info,
        **drift_info,
        model=model,
        fallback_nls=fallback.tolist(),
        cone_spread_m=spread_gp.tolist(),
        nls_cone_spread_m=spread_nls.tolist(),
        planar=np.asarray(planar).tolist(),
        bias_m=bias.tolist(),
        **{
            k: np.exp(np.asarray(v)).tolist()
            for k, v in zip(names, (hyp.log_length, hyp.log_variance, hyp.log_noise), strict=True)
        },
    )
    kept = AnchorRanges(groups.position, groups.range, groups.mask)
    codes = np.maximum(np.asarray(codes), np.asarray(nls_codes))
    hint = f"raise max_steps (now {p.max_steps}; retried with {steps}) of the {model} GP fit"
    return finish(dataset, "gp", p, kept, est, cov, info, report_fits("gp", codes, kept, p, hint), pose_cov)
