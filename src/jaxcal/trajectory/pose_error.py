"""A stated pose error propagated into the anchor covariance (`pose_sd_m`, `pose_drift`).

An error of the platform's reported poses that persists along the path (odometry drift, a frame or
lever-arm offset) moves every tag position of a stretch together. An anchor ranged from that stretch
absorbs it: the fit moves with the poses, and its residuals do not show it (on the simulated campaigns
with odometry drift the fit moves by 0.1-0.7 m horizontally, about the mean pose error over the anchor's
ranges, while the residuals' spread is 0.15-0.6 m at every lag, so no statistic of the ranges can size it;
see docs/benchmarks/uncertainty.md). What the ranges cannot show must be stated: the two parameters
describe the horizontal pose error delta(t) (per axis, independent axes, no vertical part) as

    delta(t) = c + w(t - t0),   c ~ N(0, pose_sd_m^2),   w a Brownian motion of intensity pose_drift^2

with t0 the first pose (dead reckoning is tied to the frame where it starts). Its covariance between two
range times is k(s, t) = pose_sd_m^2 + pose_drift^2 min(s - t0, t - t0).

Propagation (linear, exact for the linearised fit): the range residual res_i = |p_i - a| + b - r_i
changes by u_i . delta(t_i) (u_i the unit vector from the anchor to the tag), so the weighted least-squares
fit x = (a, b) moves by -A^-1 sum_i w_i J_i u_i . delta(t_i) (J_i = d res_i / d x, A = J^T W J), whose
covariance is A^-1 M A^-1 with M = sum_h sum_ij v_i^h v_j^h^T k(t_i, t_j), v_i^h = w_i u_ih J_i. With the
ranges in time order, min(s, t) = integral of 1[z < s] 1[z < t] dz turns the double sum into one pass:
M = sum_h [pose_sd_m^2 S_1 S_1^T + pose_drift^2 sum_k (tau_k - tau_(k-1)) S_k S_k^T], S_k = sum_(i >= k) v_i
(tau_i = t_i - t0, tau_0 = 0). The weights are the Cauchy weights of `nls` at the estimate (scale
2.385 x 1.4826 x the median absolute residual about the median, at least 0.05 m).

A bounded shared error (`bounded_sd_m`, `bounded_corr_s`: a stationary error that does not grow, kernel
s^2 exp(-|s - t| / T); what `jaxcal.trajectory.drift` propagates where the ranges support it rather than a
drift) adds s^2 sum_ij v_i v_j^T exp(-|t_i - t_j| / T) to M, also in one pass: with R_i = sum_(j < i) v_j
exp(-(t_i - t_j) / T) = exp(-(t_i - t_(i-1)) / T) (R_(i-1) + v_(i-1)), the double sum is sum_i v_i v_i^T +
R_i v_i^T + v_i R_i^T (`_exp_kernel_sum`; in blocks of 20 T, where the recursion is a scaled cumulative sum).

What a jackknife already holds (`seen_by`, for an error estimated from the ranges, `jaxcal.trajectory.drift`).
nls widens its covariance to a cluster jackknife over G consecutive stretches of each anchor's ranges; a shared
error that changes between the stretches moves the leave-one-out fits, so that jackknife already holds part of it
(all of an error correlated over much less than a stretch, none of a constant one). Its expectation under the
kernel is exact for the linearised fit: leaving stretch g out moves the fit by C_g sum_(i in g) w_i J_i r_i, with
r = (I - J A^-1 J^T W) e the residuals and C_g = (A - A_g)^-1 (the leverage capped as in nls), linear in e, so
E[J] = (G - 1) / G sum_g sum_h sum_ij c_gi^h c_gj^h^T k(t_i, t_j), a kernel sum as above with the columns c_gi =
C_g (1[i in g] w_i J_i - A_g A^-1 w_i J_i) u_ih. With `seen_by` = G the covariance is the PSD part of the
propagated one less E[J]: what the stretches cannot show (the jackknife can hold more than the propagation in a
direction the fit determines mostly from one stretch; that direction gets nothing).
"""

from __future__ import annotations

import logging

import numpy as np

__all__ = ["anchor_times", "pose_error_covariance", "pose_error_covariances"]


def pose_error_covariance(
    pos: np.ndarray,
    rng: np.ndarray,
    time: np.ndarray,
    anchor: np.ndarray,
    sd_m: float,
    drift: float,
    t0: float,
    bias: bool = True,
    min_scale_m: float = 0.05,
    bounded_sd_m: float = 0.0,
    bounded_corr_s: float = 1.0,
    seen_by: int = 0,
) -> np.ndarray:
    """(3, 3) covariance [m^2] of one anchor's estimate from the stated pose error (module docstring).

    Args:
        pos: (n, 3) tag positions [m], rng: (n,) ranges [m], time: (n,) their times [s], non-decreasing.
        anchor: (3,) the estimate [m]. sd_m: pose_sd_m [m]. drift: pose_drift [m / sqrt(s)].
        t0: time of the first pose [s]. bias: the fit has a range bias (a fourth unknown).
        min_scale_m: floor of the Cauchy scale [m].
        bounded_sd_m, bounded_corr_s: sd s [m] and correlation time T [s] of a bounded shared error (kernel
            s^2 exp(-|s - t| / T), module docstring); 0 = none.
        seen_by: G > 1: only the part a cluster jackknife over G consecutive stretches of these ranges does not
            hold (the PSD part of the propagated covariance less that jackknife's expectation, module docstring).
    """
    d = np.asarray(pos, float) - np.asarray(anchor, float)
    dist = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
    u = d / dist[:, None]
    res0 = dist - np.asarray(rng, float)
    b = float(np.median(-res0)) if bias else 0.0
    res = res0 + b
    scale = max(2.385 * 1.4826 * float(np.median(np.abs(res - np.median(res)))), min_scale_m)
    w = 1.0 / (1.0 + (res / scale) ** 2)
    jac = np.column_stack([-u, np.ones(u.shape[0])]) if bias else -u
    a_mat = (jac * w[:, None]).T @ jac
    tau = np.maximum(np.asarray(time, float) - t0, 0.0)
    kernel = (sd_m, drift, bounded_sd_m, bounded_corr_s)
    a_inv = np.linalg.pinv(a_mat)
    lever = jac * w[:, None] @ a_inv  # row i: A^-1 w_i J_i, how range i's error moves the fit
    m = sum(_kernel_sum(lever * u[:, h : h + 1], tau, *kernel) for h in range(2))
    if seen_by > 1:
        m = m - _jackknife_expectation(jac, w, lever, a_mat, u, tau, kernel, seen_by)
    c = m[:3, :3]
    lam, vec = np.linalg.eigh(0.5 * (c + c.T))  # PSD by construction; rounding can leave -1e-14 on a zero axis
    return (vec * np.maximum(lam, 0.0)) @ vec.T


def _kernel_sum(v: np.ndarray, tau: np.ndarray, sd_m: float, drift: float, bounded_sd_m: float, corr_s: float):
    """sum_ij v_i v_j^T k(tau_i, tau_j) for v (n, k), tau (n,) non-decreasing [s] from the first pose, and the
    module docstring's kernel k (offset sd_m, drift, bounded error): in one pass."""
    s = np.cumsum(v[::-1], axis=0)[::-1]  # S_k = sum over i >= k of v_i
    dtau = np.diff(np.concatenate([[0.0], tau]))
    m = sd_m**2 * np.outer(s[0], s[0]) + drift**2 * (s * dtau[:, None]).T @ s
    if bounded_sd_m > 0:
        m = m + bounded_sd_m**2 * _exp_kernel_sum(v, tau, corr_s)
    return m


def _jackknife_expectation(jac, w, lever, a_mat, u, tau, kernel, n_stretches: int, max_leverage: float = 0.99):
    """E[J] (P, P): the expectation, under the pose error's kernel, of the cluster jackknife over `n_stretches`
    consecutive stretches of the linearised fit (`jaxcal.trajectory.nls.robust_covariance`, its leverage cap
    alike). Leaving stretch g out moves the fit by C_g sum_(i in g) w_i J_i r_i with r = e - J A^-1 J^T W e the
    residuals (what the fit absorbed is gone) and C_g = (A - A_g)^-1: linear in the errors e_i = u_i . delta(t_i);
    column i of the map is C_g (1[i in g] w_i J_i - A_g A^-1 w_i J_i), and its kernel sum is `_kernel_sum`'s."""
    n = jac.shape[0]
    label = (np.arange(n) * n_stretches) // max(n, 1)
    lam, vec = np.linalg.eigh(0.5 * (a_mat + a_mat.T))
    lam = np.maximum(lam, 1e-12 * max(float(np.sum(np.abs(lam))), 1e-300))
    white = vec / np.sqrt(lam)  # W^T A W = I
    jw = jac * w[:, None]
    out = np.zeros_like(a_mat)
    for g in range(n_stretches):
        inside = label == g
        a_g = jw[inside].T @ jac[inside]
        mu, v = np.linalg.eigh(white.T @ (0.5 * (a_g + a_g.T)) @ white)
        c_g = white @ (v * (1.0 / (1.0 - np.clip(mu, 0.0, max_leverage)))) @ v.T @ white.T
        cols = (jw * inside[:, None] - lever @ a_g) @ c_g  # row i: (C_g (1[i in g] w_i J_i - A_g A^-1 w_i J_i))^T
        out += sum(_kernel_sum(cols * u[:, h : h + 1], tau, *kernel) for h in range(2))
    return (n_stretches - 1) / n_stretches * out


def _exp_kernel_sum(v: np.ndarray, tau: np.ndarray, corr_s: float, block: float = 20.0) -> np.ndarray:
    """sum_ij v_i v_j^T exp(-|tau_i - tau_j| / corr_s) for v (n, k) and non-decreasing tau (n,) [s], in O(n k^2):
    the recursion of the module docstring, run as a cumulative sum of v_j exp((tau_j - tau_ref) / T) within
    blocks of `block` x T (factors at most e^20, so no overflow nor loss of the terms that matter)."""
    t = np.asarray(tau, float) / max(float(corr_s), 1e-12)
    out = v.T @ v
    carry = np.zeros(v.shape[1])  # R just after the previous block's last range, at its time
    t_prev = t[0] if t.size else 0.0
    start = 0
    while start < t.size:
        stop = int(np.searchsorted(t, t[start] + block, side="right"))
        tb, vb = t[start:stop], v[start:stop]
        grow = np.exp(tb - tb[0])
        # R_i = exp(-(t_i - t_prev)) carry + sum_(start <= j < i) v_j exp(-(t_i - t_j))
        inner = np.cumsum(vb * grow[:, None], axis=0) - vb * grow[:, None]
        r = np.exp(-(tb - t_prev))[:, None] * carry[None, :] + inner / grow[:, None]
        out += r.T @ vb + vb.T @ r
        carry, t_prev = r[-1] + vb[-1], tb[-1]
        start = stop
    return out


def anchor_times(dataset, groups) -> list[np.ndarray | None]:
    """Range times [s] of each anchor's entries of `groups`, in their order: `groups.time` where the grouping
    kept it, else the dataset's finite ranges of that anchor when their count matches the group's (None
    where it does not: ranges were dropped at pose gaps and their times are not known here)."""
    mask = np.asarray(groups.mask)
    gt = getattr(groups, "time", None)
    out: list[np.ndarray | None] = []
    for a in range(mask.shape[0]):
        if gt is not None:
            out.append(np.asarray(gt)[a][mask[a]])
            continue
        idx = np.flatnonzero((np.asarray(dataset.range_anchor) == a) & np.isfinite(np.asarray(dataset.range)))
        out.append(np.asarray(dataset.range_time, float)[idx] if idx.size == mask[a].sum() else None)
    return out


def pose_error_covariances(
    dataset, groups, est: np.ndarray, p, method: str, bounded: tuple[float, float] = (0.0, 1.0), seen_by: int = 0
) -> np.ndarray:
    """(A, 3, 3) `pose_error_covariance` of every anchor with a finite estimate (0 elsewhere) for the parameters'
    `pose_sd_m` and `pose_drift` and a bounded shared error `bounded` = (sd [m], correlation time [s]), less what a
    jackknife over `seen_by` stretches holds of it (0: nothing); an anchor whose range times are unknown
    (`anchor_times`) gets 0 and one warning line names it.
    """
    out = np.zeros((est.shape[0], 3, 3))
    if p.pose_sd_m <= 0 and p.pose_drift <= 0 and bounded[0] <= 0:
        return out
    times = anchor_times(dataset, groups)
    pos, rng, mask = (np.asarray(v) for v in (groups.position, groups.range, groups.mask))
    t0 = float(np.asarray(dataset.pose_time)[0])
    missing = []
    for a in range(est.shape[0]):
        if not np.isfinite(est[a]).all() or mask[a].sum() < 4:
            continue
        ta = times[a]
        if ta is None:
            missing.append(dataset.anchor_ids[a])
            continue
        out[a] = pose_error_covariance(
            pos[a][mask[a]],
            rng[a][mask[a]],
            ta,
            est[a],
            p.pose_sd_m,
            p.pose_drift,
            t0,
            bool(getattr(p, "bias", True)),
            float(getattr(p, "min_scale_m", 0.05)),
            *bounded,
            seen_by,
        )
    if missing:
        logging.getLogger("jaxcal").warning(
            "%s: the range times of %d anchor(s) (%s) are not known here (ranges dropped at pose gaps): the stated "
            "pose error (pose_sd_m, pose_drift) is not in their covariance",
            method,
            len(missing),
            ", ".join(missing[:8]) + (", ..." if len(missing) > 8 else ""),
        )
    return out
