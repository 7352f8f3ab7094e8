"""Robust nonlinear least squares per anchor with a range-bias term (the `nls` baseline).

Model: r_i = |p_i - a| + b + e_i with an unknown constant range bias b (antenna delay) per anchor.
Robustness by iteratively reweighted least squares (IRLS): each round solves the weighted problem with
Optimistix Levenberg-Marquardt, then updates the weights from the residuals with a Cauchy (default) or
Huber loss whose scale is `loss_scale_m`, or, when that is 0, 2.385 x the robust standard deviation
(1.4826 x MAD) of the current residuals (95 % Gaussian efficiency of the Cauchy loss), floored at
`min_scale_m`. Initialised from the linear `ls` solution. All anchors are solved at once (vmap).

Covariance (`robust_covariance`): the larger (in every direction) of the model covariance
s^2 (J^T W J)^-1 (s^2 the weighted residual variance) and a cluster-robust sandwich A^-1 B A^-1 whose
clusters are `n_clusters` consecutive stretches of the anchor's ranges in time. Range errors along a path
are not independent (multipath that persists while the platform passes, pose errors that drift): counted
as independent, thousands of ranges shrink the covariance to millimetres for errors of decimetres. The
sandwich sums the weighted residual scores per stretch, so errors that persist within a stretch count once.
The 3 x 3 position block is reported.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from jaxcal import solver as S
from jaxcal.data import Result
from jaxcal.errors import JaxcalError
from jaxcal.params import with_overrides
from jaxcal.precision import in_float64
from jaxcal.trajectory.common import TrajectoryParams, finish, multilaterate, report_fits
from jaxcal.trajectory.poses import prepare_poses

__all__ = ["NLSParams", "solve_anchor", "irls_covariance", "robust_covariance", "calibrate"]


class NLSParams(TrajectoryParams):
    """Parameters of `nls` (defaults).

    Attributes:
        loss: `cauchy`, `huber` or `l2`.
        loss_scale_m: loss scale [m]; 0 = from the residuals' MAD each round.
        min_scale_m: floor of the automatic scale [m].
        bias: estimate a constant range bias per anchor.
        n_irls: reweighting rounds. max_steps: Levenberg-Marquardt steps per round.
        n_clusters: stretches of consecutive ranges per anchor for the cluster-robust covariance.
        min_ranges, planar_tol_m, planar_ratio, side, order, knot_dt_s: as for `ls`, and so are
            max_gap_s, time_offset_s, estimate_offset, max_offset_s.
    """

    loss: str = "cauchy"
    loss_scale_m: float = 0.0
    min_scale_m: float = 0.05
    bias: bool = True
    n_irls: int = 6
    max_steps: int = 100
    n_clusters: int = 16


def _dist(pos, a):
    d2 = jnp.sum((pos - a) ** 2, axis=-1)
    safe = jnp.where(d2 > 0, d2, 1.0)
    return jnp.where(d2 > 0, jnp.sqrt(safe), 0.0)


def _weights(res, mask, loss, scale, min_scale):
    w = mask.astype(res.dtype)
    if loss == "l2":
        return w
    a = jnp.abs(res)
    if scale > 0:
        c = jnp.asarray(scale, res.dtype)
    else:
        med = jnp.nanmedian(jnp.where(mask, a, jnp.nan))
        c = jnp.maximum(2.385 * 1.4826 * med, min_scale)
    if loss == "cauchy":
        return w / (1.0 + (a / c) ** 2)
    return w * jnp.minimum(1.0, c / jnp.maximum(a, 1e-12))  # huber


def solve_anchor(pos, rng, mask, init, p: NLSParams):
    """Robust NLS for one anchor.

    Args:
        pos: (n, 3) tag positions [m]. rng: (n,) ranges [m]. mask: (n,) valid entries.
        init: (3,) initial anchor position [m]. p: parameters (static).

    Returns:
        (position (3,), covariance (3, 3), bias [m], outcome code of the last round's fit (`jaxcal.solver`)).
    """
    use_bias = 1.0 if p.bias else 0.0

    def residual(x, args):
        sw = args
        return sw * (_dist(pos, x[:3]) + use_bias * x[3] - rng)

    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)
    x = jnp.concatenate([init, jnp.zeros(1)])
    w = mask.astype(pos.dtype)

    def irls_round(carry, _):
        x, w = carry
        sol = optx.least_squares(residual, solver, x, args=jnp.sqrt(w), max_steps=p.max_steps, throw=False)
        x = sol.value
        res = _dist(pos, x[:3]) + use_bias * x[3] - rng
        return (x, _weights(res, mask, p.loss, p.loss_scale_m, p.min_scale_m)), S.outcome(sol)

    (x, w), codes = jax.lax.scan(irls_round, (x, w), None, length=p.n_irls)
    # Covariance from the Jacobian of the weighted residuals at the solution.
    sw = jnp.sqrt(w)
    jac = jax.jacfwd(residual)(x, sw)
    if not p.bias:
        jac = jac[:, :3]
    cov = irls_covariance(jac, residual(x, sw), w, mask, p.n_clusters)
    return x[:3], cov[:3, :3], x[3] * use_bias, codes[-1]


def irls_covariance(jac_w, res_w, w, mask, n_clusters: int):
    """Covariance of an IRLS fit: the model covariance s^2 (J^T W J)^-1 (s^2 the weighted residual variance
    per effective observation) widened to the cluster-robust sandwich (`robust_covariance`).

    Args:
        jac_w: (n, P) Jacobian of the weighted residuals sqrt(w) (model - range); res_w: (n,) those residuals.
        w: (n,) IRLS weights (0 on padding); mask: (n,) valid entries, in time order.
        n_clusters: stretches for the sandwich (static).

    Returns:
        (P, P) covariance.
    """
    n_w = jnp.maximum(jnp.sum(w), 1e-12)
    dof = jnp.maximum(jnp.sum(w) * jnp.sum(mask) / n_w - jac_w.shape[1], 1.0)
    s2 = jnp.sum(res_w**2) / dof * jnp.sum(mask) / n_w
    cov = s2 * jnp.linalg.pinv(jac_w.T @ jac_w)
    return robust_covariance(cov, jac_w, res_w, mask, n_clusters)


def robust_covariance(cov_model, jac_w, res_w, mask, n_clusters: int):
    """The model covariance widened, in every direction where it is smaller, to the cluster-robust sandwich.

    Args:
        cov_model: (P, P) model covariance s^2 (J^T W J)^-1.
        jac_w: (n, P) Jacobian of the weighted residuals sqrt(w) (model - range); res_w: (n,) those residuals.
        mask: (n,) valid entries, in time order (padding after them).
        n_clusters: number of consecutive stretches (static).

    Returns:
        (P, P) symmetric PSD covariance >= both cov_model and the sandwich
        G / (G - 1) A^+ (sum_g s_g s_g^T) A^+, A = J^T W J, s_g = sum over stretch g of sqrt(w) J res.
    """
    n_valid = jnp.maximum(jnp.sum(mask), 1)
    rank = jnp.cumsum(mask) - 1
    cluster = jnp.where(mask, (rank * n_clusters) // n_valid, n_clusters)
    score = jac_w * jnp.where(mask, res_w, 0.0)[:, None]
    s = jax.ops.segment_sum(score, cluster, n_clusters + 1)[:n_clusters]
    a_inv = jnp.linalg.pinv(jac_w.T @ jac_w)
    sand = n_clusters / (n_clusters - 1.0) * a_inv @ (s.T @ s) @ a_inv
    d = 0.5 * (sand + sand.T) - 0.5 * (cov_model + cov_model.T)
    lam, vec = jnp.linalg.eigh(d)
    out = 0.5 * (cov_model + cov_model.T) + (vec * jnp.maximum(lam, 0.0)) @ vec.T
    return 0.5 * (out + out.T)


@eqx.filter_jit
def _solve_all(pos, rng, mask, p: NLSParams):
    """All anchors at once: `ls` initialisation, then `solve_anchor` (vmap); `p` is static."""

    def one(ps, r, m):
        init, _ = multilaterate(ps, r, m, p.planar_tol_m, p.side, p.planar_ratio)
        init = jnp.where(jnp.isfinite(init), init, 0.0)
        return solve_anchor(ps, r, m, init, p)

    return jax.vmap(one)(pos, rng, mask)


@in_float64
def calibrate(dataset, params=None, config=None) -> Result:
    """`--method nls`: robust NLS with a range bias per anchor, initialised from `ls` (frame `world`).

    Args:
        dataset: TrajectoryDataset. params: overrides of `NLSParams`. config: ignored.

    Returns:
        Result with `position` (A, 3) and `covariance` (A, 3, 3); the fitted biases are in params.
    """
    p = with_overrides(NLSParams(), params)
    if p.loss not in ("cauchy", "huber", "l2"):
        raise JaxcalError(f"parameter loss: expected cauchy, huber or l2, got {p.loss!r}")
    groups, info = prepare_poses(dataset, p)

    (est, cov, bias, codes), codes, steps = solve_all_checked(groups, p)
    info = dict(info, bias_m=[float(b) for b in bias])
    hint = f"raise max_steps (now {p.max_steps}; retried with {steps}) or n_irls (now {p.n_irls})"
    return finish(dataset, "nls", p, groups, est, cov, info, report_fits("nls", codes, groups, p, hint))


def solve_all_checked(groups, p: NLSParams):
    """`_solve_all` on prepared `groups`, once more with 4x `max_steps` when a fit ran out of steps
    (`jaxcal.solver.retry_unconverged`). Returns ((position, covariance, bias, codes), codes, steps used)."""

    def fit(steps):
        out = _solve_all(groups.position, groups.range, groups.mask, eqx.tree_at(lambda q: q.max_steps, p, steps))
        return out, out[3]

    return S.retry_unconverged(fit, p.max_steps)
