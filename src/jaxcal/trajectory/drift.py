"""The platform's pose drift intensity estimated from the ranges, where the user did not state `pose_drift`.

Every anchor ranged at time t sees the same horizontal pose error delta(t): the range residual at the fit
(res = |p - a| + b - r) changes by u . delta(t) (u the unit vector from the anchor to the tag), exactly as a
move of the anchor by -delta would change it. Over a short cell (one anchor's ranges in `window_s`) delta is
about constant, so the cell's ranges tell its delta only through the same four columns J = (-u, 1) as the
anchor and its bias; what they tell about delta *changes* between cells, relative to the anchor's fitted
position, is the drift. A constant shift of every pose is not observable this way (the anchors move with it);
sizing it stays `pose_sd_m`'s job.

Model (linear at the fit; a linear mixed model, estimated by restricted maximum likelihood, REML):

    res_i = J_i (x_a - E delta_c - e_4 beta_c) + n_i,   n_i ~ N(0, sigma^2 / w_i)

x_a the anchor's (position, bias) correction (fixed effects: REML integrates them out, so what the fit
absorbed is accounted for), delta_c = w(t_c) + eta_c with w a Brownian motion from the first pose of
intensity q^2 per axis (`pose_error`'s model) and eta_c a horizontal shift of the anchor's cells, beta_c a
range offset of its cells (an NLOS zone passed), both per anchor with variances nu^2 and tau^2 and correlated
over exp(-|t - t'| / `LOCAL_CORR_S`) (the structure function's "window noise", but persisting over a few
cells), E = (I_2; 0; 0), e_4 the bias column, w_i the Cauchy weights of `nls` at the fit. Each cell's ranges
enter only through their projection on the cell's columns sqrt(w) J (an SVD: at most 4 numbers per cell,
sufficient for the three variances at a given sigma^2; `tests/test_drift.py` checks the likelihood against the
one written out on every range); sigma^2 is the within-cell weighted residual variance (the part no cell-level
effect reaches). (q^2, tau^2, nu^2) are fitted by REML (L-BFGS-B, analytic gradient, bounds >= 0).

What the covariance uses (`drift_for_covariance`) is not the REML value q but `upper`, the largest q within
one standard deviation (the profile log-likelihood 1/2 below its maximum): on the simulated `small` campaigns
(3 anchors, 1-3 short visits each: little to see) q is 0 on most campaigns at 0.01 m/sqrt(s) and half the
truth at 0.02 (odd seeds 1-19: medians 0.0006 and 0.0102), while the upper bound's medians are 0.0083 and
0.0187, and 0.0045 (0.003-0.016) without drift (docs/benchmarks/uncertainty.md, eleventh round). Where a
drift is present, lags between visits of an anchor carry it (q^2 L grows with the lag L, the local terms do
not); with a single short visit of every anchor there is little to see and the bound is then what the ranges
cannot exclude.

Cells are `window_s` (2 s) long, at least 4 x an anchor's median range interval (hymn: 4.9 s); at most
`max_cells` (100), evenly spaced in time, enter the likelihood (its cost is (4 cells)^3).

Which model is propagated. The random walk extrapolates a shared error seen over short lags to the whole path,
from the first pose: on the hanyang drives (233 s, anchors within 9 cm) its upper bound widened a
well-calibrated covariance about tenfold (NEES/dof 1.14 -> 0.01), on hymn-torgau (4 hours) it put 0.3 m^2 on each
horizontal axis. So a bounded alternative is fitted too: a shared stationary error of variance s^2 correlated over
exp(-|t - t'| / T) in place of the drift, T the best of `BOUNDED_CORR_S` up to the cells' span. Where it fits
within `SELECT_MARGIN` of the drift (or better), it is the model propagated (`pose_error`'s exponential kernel,
s at its one-sd upper bound as for q). With a few anchors the two are rarely told apart: on the simulated `small`
campaigns (even seeds 0-18, with and without drift) the drift fitted at most 0.39 better, on the four recordings at
most 0.04 better once T may reach the span (hymn's 10.8 in favour of the drift with T <= 180 s), and on hanyang
LOS the bounded one fits 1.2 better; so in practice it is the bounded
model, whose variance does not grow with the time since the first pose.

What is added to nls's covariance is the part of the propagated error that its jackknife over `cov_clusters`
stretches cannot see (`pose_error`'s `seen_by`): that covariance is already widened to the jackknife, which
holds an error that changes between the stretches (on hanyang LOS, 20 s against stretches of ~58 s: all of it),
so adding the whole propagation counted it twice (twelfth round: NEES/dof 1.14 -> 0.19 there). On by default in nls
(`estimate_drift`) since the thirteenth round; on the simulated drift family the worst campaign stays above 3
(docs/benchmarks/uncertainty.md, thirteenth round). `gp` (every model that starts from nls) adds the same term
since the fourteenth round (`drift_for_method`): the estimate at nls's fit, made once, as nls would make it.
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import equinox as eqx
import numpy as np
from scipy.optimize import brentq, minimize

from jaxcal.blas_threads import one_blas_thread
from jaxcal.trajectory.common import cauchy_weights
from jaxcal.trajectory.pose_error import anchor_times, pose_error_covariances

__all__ = [
    "MODELS",
    "DriftEstimate",
    "cell_statistics",
    "reml_terms",
    "reml_loglik",
    "estimate_drift",
    "drift_for_covariance",
    "drift_for_method",
]

SCALES = np.array([1e-4, 1e-2, 1e-2])  # typical q^2 [m^2/s], tau^2 and nu^2 [m^2]: the optimiser's units
UPPER_DROP = 0.5  # the upper bound: where the profile REML log-likelihood is this far below its maximum (1 sd)
# correlation times [s] of the bounded alternative to the drift (those up to the cells' span are tried)
BOUNDED_CORR_S = (20.0, 60.0, 180.0, 600.0, 1800.0, 5400.0)
# the bounded alternative is propagated where it fits at most this much worse [log-likelihood] than the drift
SELECT_MARGIN = 2.0
# `drift_model`: what the user knows of the pose source. A relative one (odometry, visual-inertial, wheel) drifts
# from the first pose, an absolute one (motion capture, total station, RTK) has a bounded error; "auto": the data
MODELS = ("auto", "drift", "bounded")
WIDENED = 0.005  # the line is written where an anchor's horizontal sd grows by more than this share
LOCAL_CORR_S = 2.5  # correlation time [s] of the per-anchor offsets and shifts (chosen on odd seeds, against 5 and 10)


class DriftEstimate(NamedTuple):
    """Result of `estimate_drift`.

    Attributes:
        drift: the REML estimate of the intensity q [m / sqrt(s)] (0 when the ranges show none; NaN when too
            few cells).
        upper: the largest q the ranges do not rule out at one standard deviation (profile REML log-likelihood
            within `UPPER_DROP` of its maximum, the other variances refitted) [m / sqrt(s)]; what the
            covariance uses (`drift_for_covariance`).
        offset_sd_m: tau [m], the per-cell range offset sd. nugget_sd_m: nu [m], the per-cell shift sd.
        noise_sd_m: sigma [m], the within-cell noise sd (fixed, not fitted).
        cells: cells used. log_lr: REML log-likelihood of the estimate minus that at q = 0 (>= 0).
        log_lr_bounded: the estimate's REML log-likelihood minus the best with a shared error that does not
            grow (correlated over each of `BOUNDED_CORR_S`) in place of the drift.
        model: "drift" or "bounded", the one `drift_for_covariance` propagates: "bounded" where the bounded
            alternative fits within `SELECT_MARGIN` of the drift (or better).
        bounded_sd_m, bounded_upper_m, bounded_corr_s: the bounded alternative's REML sd s [m], its one-sd upper
            bound (as `upper`) [m] and its correlation time T [s] (the best of `BOUNDED_CORR_S` up to the span).
    """

    drift: float
    upper: float
    offset_sd_m: float
    nugget_sd_m: float
    noise_sd_m: float
    cells: int
    log_lr: float
    log_lr_bounded: float
    model: str = "drift"
    bounded_sd_m: float = float("nan")
    bounded_upper_m: float = float("nan")
    bounded_corr_s: float = float("nan")


def cell_statistics(anchors, t0: float, window_s: float, min_scale_m: float = 0.05, min_ranges: int = 3):
    """Per cell (one anchor's ranges in one `window_s` interval from t0) the whitened statistics of the module
    docstring.

    Args:
        anchors: list of (pos (n, 3) [m], rng (n,) [m], time (n,) [s], anchor (3,) [m], bias [m]) at the fit.
        t0: time of the first pose [s]. window_s: cell length [s]. min_scale_m: floor of the Cauchy scale.
        min_ranges: cells with fewer ranges are left out.

    Returns:
        (cells: list of (anchor index, cell time - t0 [s], B (k, 4), y (k,)), sigma^2, within-cell dof), where
        y = B (x_a - E delta - e_4 beta) + N(0, sigma^2 I) and B^T B = F_c.
    """
    cells = []
    rss, dof = 0.0, 0
    for k, (pos, rng, time, anchor, bias) in enumerate(anchors):
        d = np.asarray(pos, float) - np.asarray(anchor, float)
        dist = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        u = d / dist[:, None]
        res = dist + bias - np.asarray(rng, float)
        w = cauchy_weights(res, min_scale_m, center=True)
        jac = np.column_stack([-u, np.ones(u.shape[0])])
        tau = np.asarray(time, float) - t0
        label = np.floor(tau / window_s).astype(np.int64)
        for c in np.unique(label):
            idx = label == c
            if idx.sum() < min_ranges:
                continue
            sw = np.sqrt(w[idx])
            # the cell's ranges in the orthonormal basis of their columns sqrt(w) J (an SVD: F_c = B^T B)
            left, sv, right_t = np.linalg.svd(jac[idx] * sw[:, None], full_matrices=False)
            keep = sv > 1e-7 * max(sv[0], 1e-300)
            y = left[:, keep].T @ (sw * res[idx])
            b = sv[keep, None] * right_t[keep]
            rss += float(np.sum(w[idx] * res[idx] ** 2) - y @ y)
            dof += int(idx.sum()) - int(keep.sum())
            cells.append((k, float(np.average(tau[idx], weights=w[idx])), b, y))
    sigma2 = rss / dof if dof > 0 else float("nan")
    return cells, max(sigma2, 1e-12), dof


def reml_terms(cells, n_anchors: int, corr_s: float = LOCAL_CORR_S, bounded_s: float | None = None):
    """Stacked design of `cells`: y (m,), X (m, 4 A) fixed effects, and the three covariance terms (m, m) per
    unit variance: G_q (the Brownian drift, shared by every anchor), G_tau (range offsets) and G_nu (horizontal
    shifts), the last two per anchor and correlated over exp(-|t - t'| / corr_s) between its cells. With
    `bounded_s`, G_q is instead a shared horizontal error that does not grow (stationary, correlated over
    exp(-|t - t'| / bounded_s)), per unit of 0.01 m^2 (the scale of the Brownian's 1e-4 m^2/s in `SCALES`)."""
    rows = [c[2] for c in cells]
    m = sum(r.shape[0] for r in rows)
    n_c = len(cells)
    y = np.concatenate([c[3] for c in cells])
    x = np.zeros((m, 4 * n_anchors))
    zd = np.zeros((m, 2 * n_c))
    zb = np.zeros((m, n_c))
    t = np.array([c[1] for c in cells])
    anchor = np.array([c[0] for c in cells])
    i = 0
    for j, (a, _, b, _) in enumerate(cells):
        k = b.shape[0]
        x[i : i + k, 4 * a : 4 * a + 4] = b
        zd[i : i + k, 2 * j : 2 * j + 2] = -b[:, :2]
        zb[i : i + k, j] = -b[:, 3]
        i += k
    if bounded_s is None:
        kmin = np.minimum(t[:, None], t[None, :])
    else:
        kmin = 100.0 * np.exp(-np.abs(t[:, None] - t[None, :]) / bounded_s)
    local = np.exp(-np.abs(t[:, None] - t[None, :]) / max(corr_s, 1e-9)) * (anchor[:, None] == anchor[None, :])
    g_q = zd @ np.kron(kmin, np.eye(2)) @ zd.T
    return y, x, (g_q, zb @ local @ zb.T, zd @ np.kron(local, np.eye(2)) @ zd.T)


def reml_loglik(theta, sigma2: float, y, x, terms, grad: bool = False):
    """REML log-likelihood (up to a constant) of the variances theta = (q^2, tau^2, nu^2) at noise sigma^2:
    -1/2 (log|V| + log|X^T V^-1 X| + y^T P y), V = sigma^2 I + sum theta_k G_k, P the REML projection
    V^-1 - V^-1 X (X^T V^-1 X)^+ X^T V^-1 (X's columns that the cells do not determine, an anchor without
    cells, are dropped). With `grad`, also its gradient in theta: -1/2 (tr(P G_k) - y^T P G_k P y)."""
    v = sigma2 * np.eye(y.size) + sum(th * g for th, g in zip(theta, terms, strict=True))
    chol = np.linalg.cholesky(v)
    vi = np.linalg.inv(chol)  # L^-1: V^-1 = L^-T L^-1
    vi_y, vi_x = vi @ y, vi @ x
    a = vi_x.T @ vi_x
    lam, vec = np.linalg.eigh(0.5 * (a + a.T))
    keep = lam > 1e-10 * max(lam[-1], 1e-300)
    proj = vi_x @ vec[:, keep] / np.sqrt(lam[keep])  # orthonormal basis of L^-1 X's column space
    white = vi_y - proj @ (proj.T @ vi_y)
    ll = -0.5 * (2.0 * np.sum(np.log(np.diag(chol))) + np.sum(np.log(lam[keep])) + white @ white)
    if not grad:
        return ll
    root = vi.T - (vi.T @ proj) @ proj.T  # P = root root^T
    p_y = vi.T @ white
    p_mat = root @ root.T
    g = np.array([-0.5 * (np.sum(p_mat * gk) - p_y @ gk @ p_y) for gk in terms])
    return ll, g


@one_blas_thread
def estimate_drift(
    anchors,
    t0: float,
    window_s: float = 2.0,
    max_cells: int = 100,
    min_scale_m: float = 0.05,
    min_cells: int = 6,
    corr_s: float = LOCAL_CORR_S,
    model: str = "auto",
) -> DriftEstimate:
    """REML estimate of the pose drift intensity from the ranges at a fit (module docstring).

    Args:
        anchors: list of (pos (n, 3) [m], rng (n,) [m], time (n,) [s, in order], anchor (3,) [m], bias [m]).
        t0: time of the first pose [s]. window_s: cell length [s] (at least 4 x the median interval between an
            anchor's ranges). max_cells: at most this many cells, evenly spaced in time, enter the likelihood (it
            costs (4 cells)^3; sigma^2 is from every cell). min_scale_m: Cauchy scale floor [m].
        min_cells: fewer usable cells give NaN. corr_s: correlation time [s] of the local terms.
        model: which shared error is propagated (`DriftEstimate.model`): "auto" (the bounded one where it fits
            within `SELECT_MARGIN` of the drift, else the drift), "drift" or "bounded" (what the user knows of the
            pose source, which the ranges cannot tell apart; `MODELS`).
    """
    gaps = [float(np.median(np.diff(a[2]))) for a in anchors if len(a[2]) > 1]
    window_s = max(window_s, 4.0 * float(np.median(gaps))) if gaps else window_s  # about 4 ranges a cell at least
    cells, sigma2, _ = cell_statistics(anchors, t0, window_s, min_scale_m)
    if len(cells) > max_cells:  # evenly spaced cells in time: the model (delta constant over a cell) holds as is
        order = np.argsort([c[1] for c in cells], kind="stable")
        cells = [cells[i] for i in order[np.round(np.linspace(0, len(cells) - 1, max_cells)).astype(int)]]
    if len(cells) < min_cells or not np.isfinite(sigma2):
        nan = float("nan")
        return DriftEstimate(nan, nan, nan, nan, float(np.sqrt(sigma2)), len(cells), 0.0, 0.0)
    y, x, terms = reml_terms(cells, len(anchors), corr_s)

    def neg(z, fixed_q2, terms):
        if fixed_q2 is None:
            ll, g = reml_loglik(np.maximum(z, 0.0) * SCALES, sigma2, y, x, terms, grad=True)
            return -ll, -g * SCALES
        ll, g = reml_loglik(np.array([fixed_q2, *(np.maximum(z, 0.0) * SCALES[1:])]), sigma2, y, x, terms, grad=True)
        return -ll, -g[1:] * SCALES[1:]

    def fit(z0, fixed_q2=None, terms=terms):
        k = 3 if fixed_q2 is None else 2
        return minimize(
            neg, np.asarray(z0, float), args=(fixed_q2, terms), jac=True, method="L-BFGS-B", bounds=[(0, None)] * k
        )

    null = min((fit(z, 0.0) for z in ([1.0, 1.0], [0.1, 0.1])), key=lambda r: r.fun)
    full = min((fit([q, *null.x]) for q in (0.0, 1.0, 4.0)), key=lambda r: r.fun)
    if full.fun >= null.fun:
        theta, top = np.array([0.0, *null.x]) * SCALES, -null.fun
    else:
        theta, top = full.x * SCALES, -full.fun
    nuisance0 = theta[1:] / SCALES[1:]
    nuisance = nuisance0.copy()

    def upper_bound(value: float, peak: float, unit: float, start: float, limit: float, terms) -> float:
        """The largest x (theta_0 = unit x^2) whose profile log-likelihood is within `UPPER_DROP` of `peak`, the
        other variances refitted; inf where it is above `limit`."""
        nonlocal nuisance
        nuisance = nuisance0.copy()

        def gap(x: float) -> float:  # profile log-likelihood at x minus (its maximum - 1/2)
            nonlocal nuisance
            r = fit(nuisance, unit * x**2, terms=terms)
            nuisance = r.x
            return -r.fun - (peak - UPPER_DROP)

        hi = max(2.0 * value, start)
        while gap(hi) > 0 and hi < limit:
            hi *= 2.0
        return float(brentq(gap, value, hi, xtol=1e-4, rtol=1e-2)) if hi < limit else float("inf")

    # a shared error that does not grow (a bounded pose error), correlated over T up to the span
    span = max(c[1] for c in cells) - min(c[1] for c in cells)
    grid = [c for c in BOUNDED_CORR_S if c <= max(span, BOUNDED_CORR_S[0])]
    tried = []
    for c in grid:
        b_terms = (reml_terms(cells, len(anchors), corr_s, c)[2][0], *terms[1:])
        tried.append((min((fit([z, *nuisance0], terms=b_terms) for z in (0.0, 1.0)), key=lambda r: r.fun), c, b_terms))
    b_fit, b_corr, b_terms = min(tried, key=lambda x: x[0].fun)  # the first of equals, as the grid's order
    bounded = -b_fit.fun
    q_hat = float(np.sqrt(theta[0]))
    upper = upper_bound(q_hat, top, 1.0, 0.004, 1.0, terms)
    b_sd = float(np.sqrt(max(b_fit.x[0], 0.0) * SCALES[0] * 100.0))
    if model == "auto":
        model = "bounded" if bounded >= top - SELECT_MARGIN else "drift"
    b_upper = float("nan")
    if model == "bounded":
        nuisance0 = b_fit.x[1:].copy()
        b_upper = upper_bound(b_sd, bounded, 0.01, 0.04, 10.0, b_terms)  # theta_0 = s^2 / 100 (`reml_terms`)
    return DriftEstimate(
        q_hat,
        upper,
        float(np.sqrt(theta[1])),
        float(np.sqrt(theta[2])),
        float(np.sqrt(sigma2)),
        len(cells),
        float(top + null.fun),
        float(top - bounded),
        model,
        b_sd,
        b_upper,
        float(b_corr),
    )


def drift_for_covariance(dataset, groups, est, bias, cov, p, method: str):
    """The estimated pose error `finish` should add: none where a pose error is stated (`pose_drift` or `pose_sd_m` > 0:
    the statement wins) or `estimate_drift` is off and `drift_model` is "auto"; else `estimate_drift`'s model at the
    fit (`est` (A, 3), `bias` (A,)): the drift's upper bound, or the bounded shared error (sd's upper bound,
    correlation time), propagated through the fit (`pose_error.pose_error_covariances`) less what nls's jackknife
    over `cov_clusters` stretches of each anchor's ranges is expected to hold of it (`seen_by`; `cov` (A, 3, 3) is
    already widened to that jackknife, which sees the shared error that changes between the stretches: adding it in
    full counted that part twice), and one line (logger "jaxcal") with the values and how much it widens the anchors'
    horizontal sd over `cov`, where it does. Returns (params, info entries, extra (A, 3, 3) covariance or None).
    """
    chosen = str(getattr(p, "drift_model", "auto"))
    if p.pose_drift > 0 or p.pose_sd_m > 0 or not (getattr(p, "estimate_drift", False) or chosen != "auto"):
        return p, {}, None
    times = anchor_times(dataset, groups)
    pos, rng, mask = (np.asarray(v) for v in (groups.position, groups.range, groups.mask))
    est, bias = np.asarray(est, float), np.asarray(bias, float)
    anchors = [
        (pos[a][mask[a]], rng[a][mask[a]], times[a], est[a], float(bias[a]))
        for a in range(est.shape[0])
        if np.isfinite(est[a]).all() and mask[a].sum() >= max(p.min_ranges, 4) and times[a] is not None
    ]
    t0 = float(np.asarray(dataset.pose_time)[0])
    fit = estimate_drift(anchors, t0, min_scale_m=float(getattr(p, "min_scale_m", 0.05)), model=chosen)
    info = {"pose_drift_estimate": fit.drift, "pose_drift_upper": fit.upper, "pose_drift_cells": fit.cells}
    info.update(pose_drift_log_lr_bounded=fit.log_lr_bounded, pose_error_model=fit.model, pose_error_propagated=False)
    seen_by = int(getattr(p, "cov_clusters", 0))
    none = eqx.tree_at(lambda r: (r.pose_sd_m, r.pose_drift), p, (0.0, 0.0))
    if fit.model == "bounded":
        info.update(pose_bounded_sd_m=fit.bounded_upper_m, pose_bounded_corr_s=fit.bounded_corr_s)
        if not (np.isfinite(fit.bounded_upper_m) and fit.bounded_upper_m > 0):
            return p, info, None
        bounded = (fit.bounded_upper_m, fit.bounded_corr_s)
        extra = pose_error_covariances(dataset, groups, est, none, method, bounded, seen_by)
        what = (
            f"a bounded shared error correlated over {fit.bounded_corr_s:.0f} s of sd {fit.bounded_sd_m:.3g} m "
            f"(its upper bound within one sd, {fit.bounded_upper_m:.3g} m, is used; a random-walk drift fits "
            + (
                f"{fit.log_lr_bounded:+.1f} in log-likelihood, within {SELECT_MARGIN:g})"
                if chosen == "auto"
                else f"{fit.log_lr_bounded:+.1f} in log-likelihood; drift_model=bounded)"
            )
        )
    else:
        if not (np.isfinite(fit.upper) and fit.upper > 0):
            return p, info, None
        drift = eqx.tree_at(lambda r: r.pose_drift, none, fit.upper)
        extra = pose_error_covariances(dataset, groups, est, drift, method, seen_by=seen_by)
        what = f"a drift of {fit.drift:.3g} m/sqrt(s) (its upper bound within one sd, {fit.upper:.3g}, is used" + (
            ")" if chosen == "auto" else "; drift_model=drift)"
        )
    base = np.trace(np.asarray(cov, float)[:, :2, :2], axis1=1, axis2=2)
    ok = np.isfinite(base) & (base > 0) & np.isfinite(est).all(axis=1)
    ratio = np.sqrt(1.0 + np.trace(extra[:, :2, :2], axis1=1, axis2=2)[ok] / base[ok])
    info["pose_error_widened"] = float(np.max(ratio)) if ratio.size else 1.0
    if ratio.size and np.max(ratio) > 1.0 + WIDENED:
        seen = f"; the part nls's jackknife over {seen_by} stretches already holds left out" if seen_by > 1 else ""
        logging.getLogger("jaxcal").warning(
            "%s: pose_drift not stated: the ranges show %s (%d cells%s): it widens the anchors' horizontal sd by "
            "x%.2f median, up to x%.2f (a constant pose shift is not in it: state pose_sd_m; state pose_drift, or "
            "estimate_drift=false for exact poses)",
            method,
            what,
            fit.cells,
            seen,
            float(np.median(ratio)),
            float(np.max(ratio)),
        )
    info["pose_error_propagated"] = True
    return p, info, extra


def drift_for_method(dataset, groups, a0, b0, cov, p, p_nls, method: str):
    """`drift_for_covariance` for a method that starts from nls's fit (`gp`): the same estimate nls makes on that
    data (at nls's answer `a0` (A, 3), `b0` (A,), with nls's `p_nls`: its Cauchy scale, `min_ranges` and jackknife
    stretches `cov_clusters`), under the method's own `p`'s stated pose error (`pose_sd_m`, `pose_drift`: a
    statement wins) and `estimate_drift` / `drift_model`. The method's covariance `cov` (A, 3, 3) is at least nls's
    jackknifed one (gp floors it there), so the part that jackknife holds is left out as for nls; `cov` only sizes
    the line's widening. Returns (info entries, extra (A, 3, 3) covariance or None), as `drift_for_covariance`."""
    q = eqx.tree_at(
        lambda r: (r.pose_sd_m, r.pose_drift, r.estimate_drift, r.drift_model),
        p_nls,
        (p.pose_sd_m, p.pose_drift, p.estimate_drift, p.drift_model),
    )
    _, info, extra = drift_for_covariance(dataset, groups, a0, b0, cov, q, method)
    return info, extra
