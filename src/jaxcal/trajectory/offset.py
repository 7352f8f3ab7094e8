"""The clock offset between the pose stream and the range stream (pose clock minus range clock), its
standard deviation, and what its uncertainty does to every anchor.

A constant offset tau moves every tag position along the path: the range to anchor k changes by its range
rate times tau, r_i ~ |p(t_i + tau) - a_k| + b_k. So tau is a parameter shared by all anchors, observable
only through the range rate u_i = d|p(t_i + tau) - a_k| / d tau, and only where that rate is not constant
per anchor: a constant rate is the same as a change of the anchor's range bias b_k (a platform that stands
still, or circles an anchor at a constant distance, cannot fix it).

`estimate` fits (a_k, b_k) of every anchor and tau jointly by iteratively reweighted Gauss-Newton (Cauchy
weights with the scale of `nls`, 2.385 x 1.4826 x the median absolute residual), the anchors profiled out
by their Schur complement: per round, with H_k = J_k^T W J_k (J_k the rows (-unit vector, 1)), c_k =
J_k^T W u, the information on tau is S = sum_k (u^T W u - c_k^T H_k^-1 c_k), and the step
-sum_k (u^T W res - c_k^T H_k^-1 g_k) / S. It starts at the stated `time_offset_s` with the anchors and
biases that `nls` fits there (`jaxcal.trajectory.nls.prepare_offset`); two rounds with tau held let the
weights settle. Its variance is the largest of the model one s^2 / S and cluster sandwiches over 16 and
over 4 stretches of consecutive ranges per anchor (range errors persist along a stretch: NLOS behind a
building; few long stretches see the longer ones). Not identifiable (NaN, not applied, one line):
relative information S / sum u^T W u below `min_relative_info` (the rate is constant per anchor), a
standard deviation above a quarter of the search interval, or an estimate at its bound.

Every anchor then moves with tau by da_k / d tau = -(H_k^-1 c_k)[:3]; `finish` adds
var(tau) (da/dtau)(da/dtau)^T to the covariance of every method (`common.offset_covariances`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["OffsetFit", "estimate", "summary"]

_HOLD_ROUNDS = 2  # rounds with tau held at its start (the weights settle first)
_ROUNDS = 14  # joint rounds after them
_MAX_STEP_S = 0.2  # largest change of tau per round [s]
_MAX_ANCHOR_STEP_M = 2.0  # largest move of an anchor per round [m]


class OffsetFit(eqx.Module):
    """A clock-offset estimate.

    Attributes:
        offset_s: pose clock minus range clock [s]; NaN where the data cannot fix it.
        sd_s: its standard deviation [s] (NaN with it).
        sensitivity: (A, 3) d anchor / d offset [m/s] at the fit (0 where no anchor was fitted).
        relative_info: information on the offset left after the anchors and biases are fitted, over the
            information it would have with them known (0: a constant range rate per anchor).
        reason: why the offset is NaN ('' when it is not).
    """

    offset_s: float
    sd_s: float
    sensitivity: np.ndarray
    relative_info: float
    reason: str = ""


def _cauchy(res, ok, min_scale):
    med = jnp.nanmedian(jnp.where(ok, jnp.abs(res), jnp.nan))
    c = jnp.maximum(2.385 * 1.4826 * jnp.where(jnp.isfinite(med), med, 1.0), min_scale)
    return ok / (1.0 + (res / c) ** 2)


@eqx.filter_jit
def _fit(pos_fn, time, tag, rng, mask, a0, b0, tau0, max_offset_s, min_scale, n_clusters: int):
    """The joint fit (module doc). pos_fn(time (N,), tag (N,), tau) -> (N, 3) tag positions, traceable in tau;
    time, tag, rng, mask (A, n) per anchor in time order. Returns (tau, var_model, var_sandwich, S, sum u^T W u,
    sensitivity (A, 3))."""
    n_a, n = rng.shape

    def positions(tau):
        return pos_fn(time.reshape(-1), tag.reshape(-1), tau).reshape(n_a, n, 3)

    def linearise(tau, a, b):
        p, v = jax.jvp(positions, (tau,), (jnp.ones_like(tau),))
        ok = mask & jnp.isfinite(p).all(-1) & jnp.isfinite(v).all(-1)
        p, v = jnp.where(ok[..., None], p, 0.0), jnp.where(ok[..., None], v, 0.0)
        d = p - a[:, None, :]
        dist = jnp.sqrt(jnp.maximum(jnp.sum(d**2, -1), 1e-12))
        unit = d / dist[..., None]
        res = jnp.where(ok, dist + b[:, None] - rng, 0.0)  # model - range
        u = jnp.sum(unit * v, -1)  # d res / d tau: the range rate w.r.t. the pose clock
        jac = jnp.concatenate([-unit, jnp.ones_like(dist)[..., None]], -1)  # d res / d (a, b)
        w = jax.vmap(_cauchy, (0, 0, None))(res, ok, min_scale)
        h = jnp.einsum("ani,an,anj->aij", jac, w, jac)
        h = h + (1e-9 * jnp.trace(h, axis1=1, axis2=2)[:, None, None] + 1e-12) * jnp.eye(4)
        g = jnp.einsum("ani,an,an->ai", jac, w, res)
        c = jnp.einsum("ani,an,an->ai", jac, w, u)
        hi_c = jnp.linalg.solve(h, c[..., None])[..., 0]
        hi_g = jnp.linalg.solve(h, g[..., None])[..., 0]
        return res, u, jac, w, ok, hi_c, hi_g

    def round_(carry, joint):
        tau, a, b = carry
        res, u, jac, w, _, hi_c, hi_g = linearise(tau, a, b)
        c = jnp.einsum("ani,an,an->ai", jac, w, u)
        info = jnp.sum(jnp.einsum("an,an->a", w, u * u) - jnp.einsum("ai,ai->a", c, hi_c))
        grad = jnp.sum(jnp.einsum("an,an->a", w, u * res) - jnp.einsum("ai,ai->a", c, hi_g))
        dtau = jnp.where(joint & (info > 0), -grad / jnp.where(info > 0, info, 1.0), 0.0)
        dtau = jnp.clip(dtau, -_MAX_STEP_S, _MAX_STEP_S)
        dx = -(hi_g + hi_c * dtau)
        norm = jnp.linalg.norm(dx[:, :3], axis=1, keepdims=True)
        dx = dx * jnp.minimum(1.0, _MAX_ANCHOR_STEP_M / jnp.maximum(norm, 1e-12))
        dx = jnp.where(jnp.isfinite(dx), dx, 0.0)
        tau = jnp.clip(tau + dtau, -max_offset_s, max_offset_s)
        return (tau, a + dx[:, :3], b + dx[:, 3]), None

    joint = jnp.arange(_HOLD_ROUNDS + _ROUNDS) >= _HOLD_ROUNDS
    (tau, a, b), _ = jax.lax.scan(round_, (jnp.asarray(tau0, rng.dtype), a0, b0), joint)

    res, u, jac, w, ok, hi_c, _ = linearise(tau, a, b)
    u_p = u - jnp.einsum("ani,ai->an", jac, hi_c)  # the rate left after the anchor and bias are fitted
    info = jnp.sum(w * u_p * u_p)
    total = jnp.sum(w * u * u)
    dof = jnp.maximum(jnp.sum(w) - 4.0 * n_a - 1.0, 1.0)
    var_model = jnp.sum(w * res**2) / dof / info
    rank = jnp.cumsum(ok, axis=1) - 1
    count = jnp.maximum(jnp.sum(ok, axis=1, keepdims=True), 1)

    def sandwich(g: int):  # cluster sandwich over g consecutive stretches per anchor
        cluster = jnp.where(ok, (rank * g) // count, g)
        seg = jax.vmap(lambda v, cl: jax.ops.segment_sum(v, cl, g + 1)[:g])
        score = seg(w * u_p * res, cluster)
        used = jnp.maximum(jnp.sum(seg(ok * 1.0, cluster) > 0), 2)
        return used / (used - 1.0) * jnp.sum(score**2) / info**2

    var_sand = jnp.maximum(sandwich(n_clusters), sandwich(max(n_clusters // 4, 1)))
    return tau, var_model, var_sand, info, total, -hi_c[:, :3]


def estimate(
    pos_fn,
    range_time: np.ndarray,
    range_tag: np.ndarray,
    range_anchor: np.ndarray,
    rng: np.ndarray,
    anchors: np.ndarray,
    bias: np.ndarray,
    start_s: float = 0.0,
    max_offset_s: float = 1.0,
    max_per_anchor: int = 2000,
    min_scale_m: float = 0.05,
    n_clusters: int = 16,
    min_relative_info: float = 1e-3,
) -> OffsetFit:
    """The clock offset by the joint fit of the module doc (host side).

    Args:
        pos_fn: (time (N,), tag (N,), offset) -> (N, 3) tag positions [m] at time + offset on the pose clock,
            traceable in the offset (NaN outside the poses); a `jax.tree_util.Partial` so that its arrays are
            traced, not baked into the compiled fit.
        range_time, range_tag, range_anchor, rng: (R,) the ranges [s], [-], [-], [m] (NaN ranges are skipped).
        anchors: (A, 3) [m], bias: (A,) [m]: the anchors' fit at the start (`nls`; NaN rows are left out).
        start_s: the start (the stated offset) [s]. max_offset_s: the search interval [-max, max].
        max_per_anchor: ranges per anchor used, evenly spaced in time. min_scale_m: floor of the Cauchy scale.
        n_clusters: stretches per anchor of the sandwich variance (and a quarter as many: the larger is kept).
        min_relative_info: the identifiability bound on S / sum u^T W u.

    Returns:
        `OffsetFit`; offset and sd NaN, with a reason, when the data cannot fix the offset.
    """
    r = np.asarray(rng, dtype=float)
    a0 = np.asarray(anchors, dtype=float)
    b0 = np.asarray(bias, dtype=float)
    n_anchors = a0.shape[0]
    fitted = np.isfinite(a0).all(axis=1) & np.isfinite(b0)
    t_all = np.asarray(range_time, dtype=float)
    groups = []
    for a in range(n_anchors):
        idx = np.flatnonzero(np.isfinite(r) & (np.asarray(range_anchor) == a))
        idx = idx[np.argsort(t_all[idx], kind="stable")]
        if idx.size > max_per_anchor:
            idx = idx[np.linspace(0, idx.size - 1, max_per_anchor).round().astype(int)]
        groups.append(idx)
    n = max(1, max(g.size for g in groups))
    time = np.full((n_anchors, n), t_all[np.isfinite(t_all)].min() if t_all.size else 0.0)
    tag = np.zeros((n_anchors, n), dtype=np.asarray(range_tag).dtype)
    rr = np.zeros((n_anchors, n))
    mask = np.zeros((n_anchors, n), dtype=bool)
    for a, g in enumerate(groups):
        if g.size < 8 or not fitted[a]:  # too few to fit an anchor and its bias, or no start: left out
            continue
        time[a, : g.size], tag[a, : g.size], rr[a, : g.size], mask[a, : g.size] = t_all[g], range_tag[g], r[g], True
    if not mask.any():
        return OffsetFit(float("nan"), float("nan"), np.zeros((n_anchors, 3)), 0.0, "no anchor has 8 ranges")
    out = _fit(
        pos_fn,
        jnp.asarray(time),
        jnp.asarray(tag),
        jnp.asarray(rr),
        jnp.asarray(mask),
        jnp.asarray(np.where(fitted[:, None], a0, 0.0)),
        jnp.asarray(np.where(fitted, b0, 0.0)),
        float(start_s),
        float(max_offset_s),
        float(min_scale_m),
        int(n_clusters),
    )
    tau_a, var_model, var_sand, info, total, sens_a = (np.asarray(x, dtype=float) for x in out)
    tau = float(tau_a)
    sd = float(np.sqrt(max(var_model, var_sand))) if info > 0 else float("inf")
    rel = float(info / total) if total > 0 else 0.0
    sens = np.where(np.isfinite(sens_a), sens_a, 0.0)
    reason = ""
    if not (rel >= min_relative_info and np.isfinite(sd)):
        reason = (
            "the range rate is (nearly) constant per anchor (platform at rest, or at a constant distance), "
            f"so the offset trades with the range bias (relative information {rel:.1e})"
        )
    elif sd > 0.25 * max_offset_s:
        reason = f"its standard deviation {sd:.3f} s is above a quarter of the search interval +-{max_offset_s:g} s"
    elif abs(tau) >= max_offset_s * (1.0 - 1e-6):
        reason = f"the fit ran to the bound of the search interval +-{max_offset_s:g} s (raise max_offset_s)"
    if reason:
        return OffsetFit(float("nan"), float("nan"), sens, rel, reason)
    return OffsetFit(tau, sd, sens, rel)


def summary(fit: OffsetFit, start_s: float) -> str:
    """The one line a run prints about the offset it estimated."""
    if np.isfinite(fit.offset_s):
        return (
            f"clock offset (pose minus range) {fit.offset_s:+.4f} s +- {fit.sd_s:.4f} s (1 sd), estimated from "
            "the range rates and applied"
        )
    return f"clock offset (pose minus range) NaN: {fit.reason}; not applied (kept {start_s:g} s)"
