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
weights settle, and then each anchor's Cauchy scale is frozen (re-estimated every round, the scale moves the
fixed point and real recordings oscillated between rounds). The rounds stop when the step is below `tol`
(1 %) of tau's model sd, at most `MAX_ROUNDS` (one line when the cap is reached); a step that flips sign
without shrinking (a 2-cycle) halves the steps from then on. The rounds run and whether they converged are
reported. Its variance is the largest of the model one s^2 / S and cluster sandwiches over 16 and
over 4 stretches of consecutive ranges per anchor (range errors persist along a stretch: NLOS behind a
building; few long stretches see the longer ones), plus the part of a stated pose error (`pose_sd_m`,
`pose_drift`: the propagation of `jaxcal.trajectory.pose_error` applied to the profiled rate w u_p / S;
odometry drift along the path correlates with the range rate and leaks into tau, which no range statistic
can show). Stretches that disagree: one offset column per quarter of each anchor's ranges (the quarters
share the anchors, profiled out as above) gives each quarter's offset; Cochran's Q of their spread (cluster
sandwich within each quarter, floored at the model variance, plus the stated pose error's covariance) with a
p-value below `MIN_STRETCH_P` says the offset jumps or drifts, or the poses drift more than stated: their
mean is applied with the sd of the mean under the DerSimonian-Laird between-stretch variance (random
effects), and one line says so. Not identifiable (NaN, not applied, one line): relative information
S / sum u^T W u below `min_relative_info` (the rate is constant per anchor), a standard deviation above a
quarter of the search interval (the rounds stop early once the model sd alone is above it), or an estimate
at its bound.

Every anchor then moves with tau by da_k / d tau = -(H_k^-1 c_k)[:3]; `finish` adds
var(tau) (da/dtau)(da/dtau)^T to the covariance of every method (`common.offset_covariances`).
"""

from __future__ import annotations

import logging

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import chi2

from jaxcal.shapes import padded_length

__all__ = ["OffsetFit", "estimate", "summary"]


class OffsetFit(eqx.Module):
    """A clock-offset estimate.

    Attributes:
        offset_s: pose clock minus range clock [s]; NaN where the data cannot fix it.
        sd_s: its standard deviation [s] (NaN with it).
        sensitivity: (A, 3) d anchor / d offset [m/s] at the fit (0 where no anchor was fitted).
        relative_info: information on the offset left after the anchors and biases are fitted, over the
            information it would have with them known (0: a constant range rate per anchor).
        reason: why the offset is NaN ('' when it is not).
        rounds: joint Gauss-Newton rounds run. converged: the last step was below `tol` sd (else the cap).
        stretch_p: p-value of Cochran's Q across the stretches' offsets (NaN where not tested).
        stretch_offsets_s: each tested stretch's offset [s], in time order (a trend: the clocks' rates differ).
        pose_sd_s: the part of sd_s from the stated pose error (0 when none is stated).
    """

    offset_s: float
    sd_s: float
    sensitivity: np.ndarray
    relative_info: float
    reason: str = ""
    rounds: int = 0
    converged: bool = True
    stretch_p: float = float("nan")
    stretch_offsets_s: tuple = ()
    pose_sd_s: float = 0.0


_HOLD_ROUNDS = 2  # rounds with tau held at its start (the weights settle first)
MAX_ROUNDS = 500  # cap on the joint rounds (a warning line when reached)
_HOPELESS_AFTER = 10  # rounds after which a model sd above a quarter of the interval stops the fit (NaN anyway)
_MAX_STEP_S = 0.2  # largest change of tau per round [s]
_MAX_ANCHOR_STEP_M = 2.0  # largest move of an anchor per round [m]
MIN_STRETCH_P = 1e-5  # Cochran Q threshold (simulated `small`, odd seeds 1-19: the least p without a jump, 1.9e-4)
_STRETCHES = 4  # stretches per anchor of the Cochran Q test (the sandwich's 16 clusters nest in them)


def _scale(res, ok, min_scale):
    med = jnp.nanmedian(jnp.where(ok, jnp.abs(res), jnp.nan))
    return jnp.maximum(2.385 * 1.4826 * jnp.where(jnp.isfinite(med), med, 1.0), min_scale)


@eqx.filter_jit
def _fit(pos_fn, time, tag, rng, mask, a0, b0, tau0, max_offset_s, min_scale, tol, freeze: bool, n_clusters: int):
    """The joint fit (module doc). pos_fn(time (N,), tag (N,), tau) -> (N, 3) tag positions, traceable in tau;
    time, tag, rng, mask (A, n) per anchor in time order. Returns (tau, var_model, var_sandwich, S, sum u^T W u,
    sensitivity (A, 3), rounds, converged, and per range (A, n): weight, rate u, profiled rate u_p, residual, used,
    unit vector (A, n, 3))."""
    n_a, n = rng.shape

    def positions(tau):
        return pos_fn(time.reshape(-1), tag.reshape(-1), tau).reshape(n_a, n, 3)

    def linearise(tau, a, b, scale):
        p, v = jax.jvp(positions, (tau,), (jnp.ones_like(tau),))
        ok = mask & jnp.isfinite(p).all(-1) & jnp.isfinite(v).all(-1)
        p, v = jnp.where(ok[..., None], p, 0.0), jnp.where(ok[..., None], v, 0.0)
        d = p - a[:, None, :]
        dist = jnp.sqrt(jnp.maximum(jnp.sum(d**2, -1), 1e-12))
        unit = d / dist[..., None]
        res = jnp.where(ok, dist + b[:, None] - rng, 0.0)  # model - range
        u = jnp.sum(unit * v, -1)  # d res / d tau: the range rate w.r.t. the pose clock
        jac = jnp.concatenate([-unit, jnp.ones_like(dist)[..., None]], -1)  # d res / d (a, b)
        c_now = jax.vmap(_scale, (0, 0, None))(res, ok, min_scale)
        c_w = jnp.where(scale > 0, scale, c_now)  # frozen per-anchor scale, or re-estimated (scale 0)
        w = ok / (1.0 + (res / c_w[:, None]) ** 2)
        h = jnp.einsum("ani,an,anj->aij", jac, w, jac)
        h = h + (1e-9 * jnp.trace(h, axis1=1, axis2=2)[:, None, None] + 1e-12) * jnp.eye(4)
        g = jnp.einsum("ani,an,an->ai", jac, w, res)
        c = jnp.einsum("ani,an,an->ai", jac, w, u)
        hi_c = jnp.linalg.solve(h, c[..., None])[..., 0]
        hi_g = jnp.linalg.solve(h, g[..., None])[..., 0]
        return res, u, jac, w, ok, hi_c, hi_g, unit, c_now

    def gn(tau, a, b, scale):
        """The profiled Gauss-Newton step on tau and its model sd at (tau, a, b)."""
        res, u, jac, w, _, hi_c, hi_g, _, _ = linearise(tau, a, b, scale)
        c = jnp.einsum("ani,an,an->ai", jac, w, u)
        info = jnp.sum(jnp.einsum("an,an->a", w, u * u) - jnp.einsum("ai,ai->a", c, hi_c))
        grad = jnp.sum(jnp.einsum("an,an->a", w, u * res) - jnp.einsum("ai,ai->a", c, hi_g))
        safe = jnp.where(info > 0, info, 1.0)
        dof = jnp.maximum(jnp.sum(w) - 4.0 * n_a - 1.0, 1.0)
        sd = jnp.sqrt(jnp.sum(w * res**2) / dof / safe)
        return jnp.where(info > 0, -grad / safe, 0.0), sd, hi_c, hi_g

    def move(tau, a, b, dtau, hi_c, hi_g, damp=1.0):
        dtau = jnp.clip(dtau, -_MAX_STEP_S, _MAX_STEP_S)
        dx = -(hi_g + hi_c * dtau) * damp
        dtau = dtau * damp
        norm = jnp.linalg.norm(dx[:, :3], axis=1, keepdims=True)
        dx = dx * jnp.minimum(1.0, _MAX_ANCHOR_STEP_M / jnp.maximum(norm, 1e-12))
        dx = jnp.where(jnp.isfinite(dx), dx, 0.0)
        return jnp.clip(tau + dtau, -max_offset_s, max_offset_s), a + dx[:, :3], b + dx[:, 3]

    def hold(carry, _):
        tau, a, b = carry
        _, _, hi_c, hi_g = gn(tau, a, b, jnp.zeros(n_a))
        return move(tau, a, b, 0.0, hi_c, hi_g), None

    (tau, a, b), _ = jax.lax.scan(hold, (jnp.asarray(tau0, rng.dtype), a0, b0), None, length=_HOLD_ROUNDS)
    scale = jnp.where(freeze, linearise(tau, a, b, jnp.zeros(n_a))[-1], 0.0)

    def cond(s):
        return (s[0] < MAX_ROUNDS) & ~s[-1] & ~s[-2]

    def body(s):
        k, tau, a, b, prev, damp, _, _ = s
        dtau, sd, hi_c, hi_g = gn(tau, a, b, scale)
        # a 2-cycle (the step flips sign without shrinking) halves the steps (tau's and the anchors') from here on
        damp = jnp.where((dtau * prev < 0) & (jnp.abs(dtau) > 0.5 * jnp.abs(prev)), 0.5 * damp, damp)
        done = jnp.abs(dtau) <= tol * sd
        # the model sd alone already above a quarter of the interval: the offset will be NaN, stop wandering
        hopeless = (k >= _HOPELESS_AFTER) & (sd > 0.25 * max_offset_s)
        tau, a, b = move(tau, a, b, dtau, hi_c, hi_g, damp)
        return k + 1, tau, a, b, dtau, damp, hopeless, done

    one = jnp.ones((), rng.dtype)
    no = jnp.array(False)
    k, tau, a, b, _, _, _, done = jax.lax.while_loop(cond, body, (0, tau, a, b, 0.0 * one, one, no, no))

    res, u, jac, w, ok, hi_c, _, unit, _ = linearise(tau, a, b, scale)
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
    return tau, var_model, var_sand, info, total, -hi_c[:, :3], k, done, w, u, u_p, res, ok, unit


def _pose_cov(cols: np.ndarray, unit: np.ndarray, t: np.ndarray, sd_m: float, drift: float, t0: float) -> np.ndarray:
    """(m, m) covariance of sum_i cols[i, j] unit_i . delta(t_i) over the ranges (in time order) for the stated
    horizontal pose error delta (`jaxcal.trajectory.pose_error`: k(s, t) = sd^2 + drift^2 min(s - t0, t - t0))."""
    dt = np.diff(np.concatenate([[0.0], np.maximum(t - t0, 0.0)]))
    out = np.zeros((cols.shape[1], cols.shape[1]))
    for h in range(2):
        s = np.cumsum((cols * unit[:, h : h + 1])[::-1], axis=0)[::-1]  # S_k = sum over i >= k
        out += sd_m**2 * np.outer(s[0], s[0]) + drift**2 * (s * dt[:, None]).T @ s
    return out


def _stretch_test(w, u, u_p, res, ok, unit, t, info, s2, pose, n_clusters: int):
    """Cochran's Q of the stretches' offsets (module doc): (Q, dof, p, (m, m) pose covariance of the stretches'
    offsets and of the joint one, its last row and column, the stretches' offsets minus the joint one).
    Arrays (A, n) per anchor; pose: (sd_m, drift, t0)."""
    n_a, n = ok.shape
    rank = np.cumsum(ok, axis=1) - 1
    count = np.maximum(ok.sum(axis=1, keepdims=True), 1)
    sub = max(n_clusters // _STRETCHES, 1)
    g = np.where(ok, (rank * _STRETCHES) // count, -1)  # stretch of each range; the sandwich's clusters nest in it
    cl = np.arange(n_a)[:, None] * _STRETCHES * sub + (rank * _STRETCHES * sub) // count  # (anchor, cluster)
    wt = np.where(ok, w, 0.0)
    # one offset column per stretch, each profiled against every anchor's position and bias (shared by all)
    uu = np.where(g[..., None] == np.arange(_STRETCHES), u[..., None], 0.0)  # (A, n, G)
    jac = np.concatenate([-unit, np.ones(ok.shape + (1,))], -1)  # (A, n, 4)
    h = np.einsum("ani,an,anj->aij", jac, wt, jac) + 1e-9 * np.eye(4)
    c = np.einsum("ani,an,ang->aig", jac, wt, uu)
    up = uu - np.einsum("ani,aig->ang", jac, np.linalg.solve(h, c))
    info_m = np.einsum("ang,an,anh->gh", up, wt, up)
    keep = np.diag(info_m) > 1e-3 * info / _STRETCHES
    up, info_m = up[..., keep], info_m[np.ix_(keep, keep)]
    flat = ok.reshape(-1)
    order = np.argsort(t.reshape(-1)[flat], kind="stable")
    m = int(keep.sum())
    theta = np.zeros(m)
    var = np.zeros((m, m))
    if m >= 2:
        inv = np.linalg.inv(info_m)
        theta = -inv @ np.einsum("ang,an,an->g", up, wt, res)  # each stretch's offset minus the joint one
        # cluster sandwich, each cluster's score taken at the stretches' own offsets (they sum to 0 there)
        sc_i = (wt * res)[..., None] * up + np.einsum("ang,an,anh,h->ang", up, wt, up, theta)
        ids = cl.reshape(-1)[flat]
        score = np.zeros((n_a * _STRETCHES * sub, m))
        np.add.at(score, ids, sc_i.reshape(-1, m)[flat])
        score = score[np.any(score != 0.0, axis=1)]
        k = score.shape[0]
        sand = inv @ (k / max(k - 1.0, 1.0) * score.T @ score) @ inv
        f = np.sqrt(np.maximum(1.0, s2 * np.diag(inv) / np.maximum(np.diag(sand), 1e-300)))
        var = f[:, None] * sand * f[None, :]  # no stretch below its model variance
    # d (stretches' offsets, joint offset) / d (range residual), per range in time order: the stated pose error's part
    to_theta = np.zeros((int(flat.sum()), m))
    if m >= 2:
        to_theta = -(wt[..., None] * up).reshape(-1, m)[flat] @ np.linalg.inv(info_m)
    cols = np.column_stack([to_theta, (wt * u_p).reshape(-1)[flat] / info])[order]
    sd_m, drift, t0 = pose
    cov_pose = np.zeros((m + 1, m + 1))
    if sd_m > 0 or drift > 0:
        cov_pose = _pose_cov(cols, unit.reshape(-1, 3)[flat][order], t.reshape(-1)[flat][order], sd_m, drift, t0)
    if m < 2:
        return 0.0, 0, 1.0, cov_pose, theta, 0.0
    v = var + cov_pose[:m, :m]
    ci = np.linalg.inv(v)
    one = np.ones(m)
    r = theta - one @ ci @ theta / (one @ ci @ one)
    q = float(r @ ci @ r)
    # DerSimonian-Laird between-stretch variance t2 (moment estimate from Q), and the variance of the mean
    # offset under it (random effects): what a constant offset fitted to a varying one is worth
    t2 = max(0.0, (q - (m - 1)) / max(np.trace(ci) - one @ ci @ ci @ one / (one @ ci @ one), 1e-300))
    var_mean = float(1.0 / (one @ np.linalg.solve(v + t2 * np.eye(m), one)))
    return q, m - 1, float(chi2.sf(q, m - 1)), cov_pose, theta, var_mean


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
    tol: float = 0.01,
    freeze_scale: bool = True,
    min_stretch_p: float = MIN_STRETCH_P,
    pose_sd_m: float = 0.0,
    pose_drift: float = 0.0,
    pose_t0: float | None = None,
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
        tol: converged when the Gauss-Newton step on the offset is below tol x its model sd.
        freeze_scale: keep the Cauchy scale of each anchor fixed after the hold rounds (else re-estimated
            every round, which moves the fixed point).
        min_stretch_p: below this p-value of Cochran's Q across the stretches, the sd is widened to their spread.
        pose_sd_m, pose_drift, pose_t0: the stated horizontal pose error (`jaxcal.trajectory.pose_error`) and
            the time of the first pose [s] (None: the first range); they widen the offset's sd.

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
    n = padded_length(max(1, max(g.size for g in groups)))  # one shape for campaigns of similar size
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
        float(tol),
        bool(freeze_scale),
        int(n_clusters),
    )
    tau_a, var_model, var_sand, info, total, sens_a = (np.asarray(x, dtype=float) for x in out[:6])
    rounds, converged = int(out[6]), bool(out[7])
    w, u, u_p, res, unit = (np.asarray(x, dtype=float) for x in (out[8], out[9], out[10], out[11], out[13]))
    ok = np.asarray(out[12], dtype=bool)
    tau = float(tau_a)
    t0 = float(np.nanmin(t_all)) if pose_t0 is None else float(pose_t0)
    q, dof, p_q, cov_pose, theta, var_mean = _stretch_test(
        w, u, u_p, res, ok, unit, time, float(info), float(var_model * info), (pose_sd_m, pose_drift, t0), n_clusters
    )
    var_pose = float(cov_pose[-1, -1])
    sd = float(np.sqrt(max(var_model, var_sand) + var_pose)) if info > 0 else float("inf")
    varies = dof > 0 and p_q < min_stretch_p
    if varies:  # the stretches disagree: the offset varies along the recording; the mean with its random-effects sd
        sd = max(sd, float(np.sqrt(var_mean)))
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
    log = logging.getLogger("jaxcal")
    if not converged and not reason:
        log.warning(
            "clock offset: the joint fit did not converge in %d rounds (last step above %g sd); its estimate is "
            "where it stopped",
            rounds,
            tol,
        )
    if varies and not reason:
        log.warning(
            "clock offset: the %d stretches of the ranges disagree on it beyond their sd (Cochran Q %.1f on %d dof, "
            "p %.1e < %g; their offsets %s s): the offset drifts or jumps, or the poses drift more than stated; "
            "their mean is applied with the sd widened to their spread (+-%.4f s)",
            dof + 1,
            q,
            dof,
            p_q,
            min_stretch_p,
            ", ".join(f"{tau + x:+.3f}" for x in theta),
            sd,
        )
    p_out, stretches = (p_q if dof > 0 else float("nan")), tuple(float(tau + x) for x in theta)
    if reason:
        return OffsetFit(float("nan"), float("nan"), sens, rel, reason, rounds, converged, p_out, stretches)
    return OffsetFit(tau, sd, sens, rel, "", rounds, converged, p_out, stretches, float(np.sqrt(var_pose)))


def summary(fit: OffsetFit, start_s: float) -> str:
    """The one line a run prints about the offset it estimated."""
    if np.isfinite(fit.offset_s):
        return (
            f"clock offset (pose minus range) {fit.offset_s:+.4f} s +- {fit.sd_s:.4f} s (1 sd), estimated from "
            f"the range rates and applied ({fit.rounds} rounds{'' if fit.converged else ', not converged'}, "
            f"stretches' Q p {fit.stretch_p:.2g})"
        )
    return f"clock offset (pose minus range) NaN: {fit.reason}; not applied (kept {start_s:g} s)"
