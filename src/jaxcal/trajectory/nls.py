"""Robust nonlinear least squares per anchor with a range-bias term (the `nls` baseline).

Model: r_i = |p_i - a| + b + e_i with an unknown constant range bias b (antenna delay) per anchor.
Robustness by iteratively reweighted least squares (IRLS): each round solves the weighted problem with
Optimistix Levenberg-Marquardt, then updates the weights from the residuals with a Cauchy (default) or
Huber loss whose scale is `loss_scale_m`, or, when that is 0, 2.385 x the robust standard deviation
(1.4826 x MAD) of the current residuals (95 % Gaussian efficiency of the Cauchy loss), floored at
`min_scale_m`. Initialised from the linear `ls` solution. All anchors are solved at once (vmap).

Covariance (`robust_covariance`): the larger (in every direction) of the model covariance
s^2 (J^T W J)^-1 (s^2 the weighted residual variance) and cluster jackknifes over `cov_clusters` and
`n_clusters` consecutive stretches of the anchor's ranges in time (the spread of the leave-one-stretch-out fits).
Range errors along a path are not independent (an NLOS state that persists while the platform passes a
building, pose errors that drift): counted as independent, thousands of ranges shrink the covariance to
millimetres for errors of decimetres; and an error that persists along a stretch pulls the fit towards
itself, so the residuals show only part of it (the leave-one-out fit does not see it at all).
`calibrate` then widens it to a third jackknife over route cells (`cov_cell_m`, `cell_covariances`): the
ranges taken in one place on every pass are one cluster, so an error tied to a place (an NLOS zone driven
through on every lap) is not counted once per lap. The 3 x 3 position block is reported.
"""

from __future__ import annotations

import logging

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxcal import solver as S
from jaxcal.data import Result
from jaxcal.errors import JaxcalError
from jaxcal.params import with_overrides
from jaxcal.precision import in_float64
from jaxcal.shapes import padded_length
from jaxcal.trajectory.common import TrajectoryParams, finish, multilaterate, report_fits, widen_covariance
from jaxcal.trajectory.drift import MODELS, drift_for_covariance
from jaxcal.trajectory.offset import summary
from jaxcal.trajectory.poses import estimate_offset_fit, fit_poses, prepare, prepare_poses

__all__ = [
    "NLSParams",
    "solve_anchor",
    "covariance_at",
    "covariances_at",
    "irls_covariance",
    "robust_covariance",
    "cell_labels",
    "route_cells",
    "cell_covariances",
    "calibrate",
    "prepare_offset",
]


class NLSParams(TrajectoryParams):
    """Parameters of `nls` (defaults).

    Attributes:
        loss: `cauchy`, `huber` or `l2`.
        loss_scale_m: loss scale [m]; 0 = from the residuals' MAD each round.
        min_scale_m: floor of the automatic scale [m].
        bias: estimate a constant range bias per anchor.
        n_irls: reweighting rounds. max_steps: Levenberg-Marquardt steps per round.
        n_clusters: stretches of consecutive ranges per anchor for the mirror-image check's variance
            (`jaxcal.trajectory.mirror`).
        cov_clusters: the covariance is the larger (in every direction) of the cluster jackknifes over
            cov_clusters and over n_clusters consecutive stretches of each anchor's ranges
            (`robust_covariance`). Few long stretches see errors that persist over a whole pass of the
            platform (an NLOS state, pose drift); on the simulated campaigns (development seeds
            200-223, 1-3 passes per anchor, horizontal NEES/dof before the mirror check) 16 stretches
            alone gave a median of 7.8 / 19.6 (no drift / drift), 4 alone 3.9 / 2.0, both 2.8 / 1.9;
            4 alone is noisy where the path has many passes (hanyang LOS: 15.6 where 16 gave 1.45).
        cov_cell_m: side [m] of the square route cells of a third jackknife (`cell_covariances`): the ranges
            taken in one cell, on every pass, are one cluster, so an error tied to a place (an NLOS zone the
            route drives through on every lap) counts once. Chosen on the development campaigns (even seeds
            0-38, no drift; cells of 1-24 m): 12 m. 0 = the scale-free cells of `cov_cells` instead.
        cov_cells: where `cov_cell_m` is 0, the box of each anchor's tag positions is cut into square cells,
            `cov_cells` along its longer side (the same partition in any unit or frame; 0 = no cells).
            Not the default: 3 per side (chosen against 2 on the development campaigns, even seeds 0-32;
            about 8 m cells on `small`) made hanyang's covariances 2-10 times too wide (18 m cells, NEES/dof
            0.17 and 0.11; see docs/benchmarks/uncertainty.md, eighth round).
        cov_sectors: bearing sectors (of 360 / cov_sectors degrees, seen from the anchor's fit) of a fourth
            jackknife (`cell_covariances`; 0 = none, the default): a range error tied to the direction it comes
            from (NLOS behind the buildings on both sides of a road, ranges from far along it) moves the anchor
            the same way from every route cell and on every pass, so the cell and stretch jackknifes cannot see
            it; leaving out one direction's ranges does. An option (fourteenth round, docs/benchmarks/
            uncertainty.md): 8 sectors took the full-scale simulated campus's odd seeds 1-7 from NEES/dof 2.1-8.0
            to 0.7-1.9, but even seeds stayed at 0.7-5.7, and the recordings became too wide (cuhksz-planar 0.31,
            hanyang LOS 0.58).
        estimate_offset: fit the pose/range clock offset jointly with the anchors (`prepare_offset`), from
            `time_offset_s` within +-`max_offset_s`: on by default for `nls` and `gp` (off for `ls`). Chosen on
            the simulated `small` family (even seeds; issue #19): where the clocks agree it changed the
            horizontal error by a median factor of 1.00, with an offset in +-0.3 s it halved it.
        estimate_drift: where no pose error is stated (`pose_drift` and `pose_sd_m` 0), estimate the poses' shared
            error from the ranges at the fit (`jaxcal.trajectory.drift`) and add to the covariance the part of it
            that the jackknife over `cov_clusters` stretches cannot see (`pose_error.pose_error_covariance`'s
            `seen_by`: an error that changes between the stretches is already in that jackknife; adding it in full
            counted it twice, eleventh and twelfth rounds): a bounded shared error (sd at its one-sd upper bound,
            correlated over a fitted time) where that fits about as well as a random-walk drift, else the drift's
            upper bound; one line says what and how much it widened the anchors' sd, where it did. A stated
            `pose_drift` or `pose_sd_m` > 0 always wins (added in full). A constant pose shift is not in it
            (`pose_sd_m`). On by default since the thirteenth round (false: poses taken as exact): on the four
            recordings it gives NEES/dof 1.08-1.62 against 1.14-6.05 off (hymn 6.05 -> 1.08, hanyang NLOS 3.87 ->
            1.62, LOS 1.14 unchanged); on the simulated drift family (even seeds) the worst campaign falls from 30.5
            to 4.3 (still above 3: `auto` mostly propagates a short bounded error there, while the poses truly
            drift; say `drift_model=drift` for odometry), the clean family's median from 0.41 to 0.31 (wider).
            It costs a REML fit after the fit (about 5 s on hanyang LOS; docs/benchmarks/uncertainty.md,
            thirteenth round).
        drift_model: which shared pose error `estimate_drift` propagates: "auto" (as above: the ranges rarely tell
            the two apart, so mostly the bounded one), "drift" (a relative pose source: odometry, visual-inertial,
            wheel; its error grows from the first pose) or "bounded" (an absolute one: motion capture, total
            station, RTK). "drift" or "bounded" turns `estimate_drift` on.
        min_ranges, planar_tol_m, planar_ratio, side, order, knot_dt_s: as for `ls`, and so are
            max_gap_s, time_offset_s, max_offset_s.
    """

    estimate_offset: bool = True
    estimate_drift: bool = True
    drift_model: str = "auto"
    loss: str = "cauchy"
    loss_scale_m: float = 0.0
    min_scale_m: float = 0.05
    bias: bool = True
    n_irls: int = 6
    max_steps: int = 100
    n_clusters: int = 16
    cov_clusters: int = 4
    cov_cell_m: float = 12.0
    cov_cells: float = 3.0
    cov_sectors: int = 0


MAX_LEVERAGE = 0.99  # the largest share of a direction's information one left-out stretch may hold
START_PER_ANCHOR = 2000  # ranges per anchor of the start fit of `prepare_offset`


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


def solve_anchor(pos, rng, mask, init, p: NLSParams, with_cov: bool = True):
    """Robust NLS for one anchor.

    Args:
        pos: (n, 3) tag positions [m]. rng: (n,) ranges [m]. mask: (n,) valid entries.
        init: (3,) initial anchor position [m]. p: parameters (static).
        with_cov: compute the covariance (static; False: NaN, a program without the jackknifes, which are most
            of its XLA compilation: the fit alone compiles in about a third of the time).

    Returns:
        (position (3,), covariance (3, 3), bias [m], outcome code of the last round's fit (`jaxcal.solver`)).
    """
    use_bias = 1.0 if p.bias else 0.0

    def residual(x, args):
        sw = args
        return sw * (_dist(pos, x[:3]) + use_bias * x[3] - rng)

    solver: optx.AbstractLeastSquaresSolver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)
    x = jnp.concatenate([init, jnp.zeros(1)])
    w = mask.astype(pos.dtype)

    def irls_round(carry, _):
        x, w = carry
        sol = optx.least_squares(residual, solver, x, args=jnp.sqrt(w), max_steps=p.max_steps, throw=False)
        x = sol.value
        res = _dist(pos, x[:3]) + use_bias * x[3] - rng
        return (x, _weights(res, mask, p.loss, p.loss_scale_m, p.min_scale_m)), S.outcome(sol)

    (x, _), codes = jax.lax.scan(irls_round, (x, w), None, length=p.n_irls)
    if not with_cov:
        return x[:3], jnp.full((3, 3), jnp.nan, x.dtype), x[3] * use_bias, codes[-1]
    cov = covariance_at(pos, rng, mask, x, p, (p.cov_clusters, p.n_clusters))
    return x[:3], cov, x[3] * use_bias, codes[-1]


def covariance_at(pos, rng, mask, x, p: NLSParams, n_clusters: tuple[int, ...]):
    """The 3 x 3 position block of `irls_covariance` at the fit x = (anchor, bias) (4,) of one anchor, with
    the IRLS weights of its residuals (the weights of `solve_anchor`'s last round).

    Args:
        pos: (n, 3) [m]. rng: (n,) [m]. mask: (n,) valid, in time order. x: (4,) anchor [m] and bias [m].
        p: parameters (static; loss, scales, bias). n_clusters: the jackknifes' stretch counts (static;
            () = the model covariance s^2 (J^T W J)^-1 alone).
    """
    use_bias = 1.0 if p.bias else 0.0

    def residual(x, sw):
        return sw * (_dist(pos, x[:3]) + use_bias * x[3] - rng)

    w = _weights(residual(x, 1.0), mask, p.loss, p.loss_scale_m, p.min_scale_m)
    sw = jnp.sqrt(w)
    jac = jax.jacfwd(residual)(x, sw)
    if not p.bias:
        jac = jac[:, :3]
    return irls_covariance(jac, residual(x, sw), w, mask, n_clusters)[:3, :3]


@eqx.filter_jit
def covariances_at(pos, rng, mask, x, p: NLSParams, n_clusters: tuple[int, ...]):
    """`covariance_at` for every anchor (vmap): pos (A, n, 3), rng and mask (A, n), x (A, 4); -> (A, 3, 3)."""
    return jax.vmap(lambda ps, r, m, xa: covariance_at(ps, r, m, xa, p, n_clusters))(pos, rng, mask, x)


def cell_labels(position: np.ndarray, mask: np.ndarray, cell_m, origin=None) -> tuple[np.ndarray, int]:
    """Route cells of the tag positions: the square (x, y) cell of side `cell_m` [m] of each valid entry,
    numbered 0, 1, ... per anchor in order of first visit.

    Args:
        position: (A, n, 3) tag positions [m]; mask: (A, n) valid entries.
        cell_m: the side [m], one for all anchors or (A,) one each. origin: (A, 2) a corner of each anchor's
            grid [m] (None: the frame's origin).

    Returns:
        ((A, n) int labels, padding = the returned count), the largest number of cells of an anchor.
    """
    side = np.broadcast_to(np.asarray(cell_m, dtype=float), mask.shape[:1])
    corner = np.zeros((mask.shape[0], 2)) if origin is None else np.asarray(origin, dtype=float)
    cells = np.floor((np.asarray(position)[..., :2] - corner[:, None, :]) / side[:, None, None]).astype(np.int64)
    mask = np.asarray(mask)
    labels = np.zeros(mask.shape, np.int64)
    counts = []
    for a in range(mask.shape[0]):
        _, first, inv = np.unique(cells[a][mask[a]], axis=0, return_index=True, return_inverse=True)
        order = np.argsort(np.argsort(first))  # numbered by first visit
        labels[a][mask[a]] = order[inv.ravel()]
        counts.append(first.size)
    n_cells = max(max(counts, default=1), 1)
    labels[~mask] = n_cells
    return labels, n_cells


def route_cells(groups, p) -> tuple[np.ndarray, int]:
    """`cell_labels` of prepared `groups` with nls's cells: `p.cov_cell_m` [m] where > 0, else the box of each
    anchor's tag positions (x, y) cut into `p.cov_cells` cells along its longer side (square cells from the
    box's corner, the last row and column clipped to the box). Parameters without them (those of `ls` and
    `gp`) get nls's defaults. Off (both 0): one cell, (A, n) zeros and padding 1. The count of cells is padded
    (`jaxcal.shapes.padded_length`; empty cells count for nothing wherever cells are used) so that campaigns of
    similar size share the compiled programs that take it as a static number."""
    side_m = float(getattr(p, "cov_cell_m", NLSParams.cov_cell_m))
    per_side = float(getattr(p, "cov_cells", NLSParams.cov_cells))
    pos, mask = np.asarray(groups.position), np.asarray(groups.mask)
    if side_m <= 0 and per_side <= 0:
        return np.where(mask, 0, 1).astype(np.int64), 1
    labels, n_cells = _route_cells(pos, mask, side_m, per_side)
    padded = padded_length(n_cells) if n_cells > 1 else n_cells
    return np.where(labels == n_cells, padded, labels), padded


def _route_cells(pos: np.ndarray, mask: np.ndarray, side_m: float, per_side: float) -> tuple[np.ndarray, int]:
    if side_m > 0:
        return cell_labels(pos, mask, side_m)
    xy = np.where(mask[..., None], pos[..., :2], np.nan)
    with np.errstate(all="ignore"):
        lo, hi = np.nanmin(xy, axis=1), np.nanmax(xy, axis=1)
    lo, hi = np.nan_to_num(lo), np.nan_to_num(hi)
    side = np.maximum(np.max(hi - lo, axis=1) / per_side, 1e-9)
    # the far edge of the box belongs to the last cell (not a cell of its own)
    inside = np.where(mask[..., None], pos[..., :2], lo[:, None, :])
    clipped = np.minimum(inside, lo[:, None, :] + (np.ceil(per_side) - 0.5) * side[:, None, None])
    return cell_labels(np.concatenate([clipped, pos[..., 2:]], axis=-1), mask, side, lo)


@eqx.filter_jit
def _cell_jackknife(pos, rng, mask, x, cells, p: NLSParams, n_cells: int):
    """`covariance_at`'s model covariance widened to the cluster jackknife over route cells (vmap over anchors):
    pos (A, n, 3), rng, mask and cells (A, n), x (A, 4) -> (A, 3, 3)."""
    use_bias = 1.0 if p.bias else 0.0

    def one(ps, r, m, xa, c):
        def residual(x, sw):
            return sw * (_dist(ps, x[:3]) + use_bias * x[3] - r)

        sw = jnp.sqrt(_weights(residual(xa, 1.0), m, p.loss, p.loss_scale_m, p.min_scale_m))
        jac = jax.jacfwd(residual)(xa, sw)
        if not p.bias:
            jac = jac[:, :3]
        zero = jnp.zeros((jac.shape[1], jac.shape[1]))
        return robust_covariance(zero, jac, residual(xa, sw), m, n_cells, c)[:3, :3]

    return jax.vmap(one)(pos, rng, mask, x, cells)


def sector_labels(position: np.ndarray, mask: np.ndarray, est: np.ndarray, n_sectors: int) -> np.ndarray:
    """(A, n) bearing sector (0 .. n_sectors - 1, of 360 / n_sectors degrees) of each tag position (A, n, 3) seen
    from the anchor's fit `est` (A, 3) in the horizontal plane; `n_sectors` where `mask` is False (padding)."""
    pos = np.asarray(position, dtype=float)
    est = np.nan_to_num(np.asarray(est, dtype=float))
    ang = np.arctan2(pos[..., 1] - est[:, None, 1], pos[..., 0] - est[:, None, 0])
    lab = np.floor((ang + np.pi) / (2.0 * np.pi / n_sectors)).astype(np.int64) % n_sectors
    return np.where(np.asarray(mask), lab, n_sectors)


def cell_covariances(groups, est, bias, cov, p: NLSParams) -> np.ndarray:
    """nls's covariances `cov` (A, 3, 3) raised, in every direction where smaller, to the cluster jackknife
    over route cells (`route_cells`; `robust_covariance`) and to the one over bearing sectors seen from the
    anchor (`cov_sectors`, `sector_labels`) at the fits `est` (A, 3), `bias` (A,). Anchors without a finite
    fit keep theirs.

    Bearing sectors (fourteenth round, an option): on the full-scale simulated campus an anchor 6 m beside a
    road, seen through buildings from the south-west and south-east, was fitted 0.67 m too far north for 0.10 m
    predicted (NEES 105): the excess came from two directions in many cells and on every pass. Leaving out one
    sector of 45 degrees moves the fit by a good part of that (`NLSParams.cov_sectors` for the figures).

    Errors tied to a place repeat each time the route passes it: the stretch jackknifes in time see laps as
    independent, so a lap-by-lap repeated error shrinks with the number of laps; leaving out one cell
    (every pass through it) shows how much the fit leans on that place. Measured (nls, no drift, even
    seeds 0-38, 60 anchors; with mirror step 5): outside the 95 % ellipse 6 -> 2, worst NEES/dof 8.7 ->
    2.6; cells of 4 m changed little (errors in the simulated NLOS zones persist over more than a cell),
    24 m was worse at the worst (5.2)."""
    cov = np.array(cov, dtype=float)
    x = np.concatenate([np.nan_to_num(np.asarray(est, float)), np.nan_to_num(np.asarray(bias, float))[:, None]], 1)
    partitions = [route_cells(groups, p)]
    n_sectors = int(getattr(p, "cov_sectors", NLSParams.cov_sectors))
    if n_sectors > 1:
        partitions.append((sector_labels(groups.position, groups.mask, x[:, :3], n_sectors), n_sectors))
    for labels, n_cells in partitions:
        if n_cells <= 1:
            continue
        pos, rng, mask = groups.position, groups.range, groups.mask
        jack = np.asarray(_cell_jackknife(pos, rng, mask, jnp.asarray(x), labels, p, n_cells))
        ok = np.isfinite(est).all(axis=1) & np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(jack).all(axis=(1, 2))
        for a in np.flatnonzero(ok):
            cov[a] = widen_covariance(cov[a], jack[a])
    return cov


def irls_covariance(jac_w, res_w, w, mask, n_clusters: int | tuple[int, ...]):
    """Covariance of an IRLS fit: the model covariance s^2 (J^T W J)^-1 (s^2 the weighted residual variance
    per effective observation) widened to the cluster jackknife (`robust_covariance`) over each number of
    stretches in `n_clusters` (the larger in every direction: few long stretches see errors that persist
    over a pass, many short ones give a steadier estimate where errors do not).

    Args:
        jac_w: (n, P) Jacobian of the weighted residuals sqrt(w) (model - range); res_w: (n,) those residuals.
        w: (n,) IRLS weights (0 on padding); mask: (n,) valid entries, in time order.
        n_clusters: stretches for the jackknife, one count or several (static).

    Returns:
        (P, P) covariance.
    """
    n_w = jnp.maximum(jnp.sum(w), 1e-12)
    dof = jnp.maximum(jnp.sum(w) * jnp.sum(mask) / n_w - jac_w.shape[1], 1.0)
    s2 = jnp.sum(res_w**2) / dof * jnp.sum(mask) / n_w
    cov = s2 * jnp.linalg.pinv(jac_w.T @ jac_w)
    for g in (n_clusters,) if isinstance(n_clusters, int) else n_clusters:
        cov = robust_covariance(cov, jac_w, res_w, mask, g)
    return cov


def robust_covariance(cov_model, jac_w, res_w, mask, n_clusters: int, cluster=None):
    """The model covariance widened, in every direction where it is smaller, to the cluster jackknife.

    The cluster jackknife (CR3) is the spread of the leave-one-stretch-out fits: one Gauss-Newton step
    without stretch g moves the estimate by (A - A_g)^-1 s_g (A = J^T W J, A_g its part from stretch g,
    s_g = sum over stretch g of sqrt(w) J res), and the covariance is (G - 1) / G sum_g of their outer
    products. Unlike the plain sandwich A^-1 (sum_g s_g s_g^T) A^-1 it accounts for what the fit absorbs:
    an error that persists along a stretch pulls the estimate towards itself, and the residuals then show
    only what is left (a stretch that alone holds most of the information on a direction shows almost
    nothing). A stretch's leverage on a direction (its share of A's information there: the generalized
    eigenvalues of A_g against A) is capped at `MAX_LEVERAGE` (`_leave_one_out_steps`): a stretch without
    which a direction is not determined gives it a large variance (its step at most 1 / (1 - 0.99) = 100
    times A^-1 s_g in A's norm), not a near-infinite one from one nearly singular solve, which made a single
    stretch decide the whole ellipsoid (docs/benchmarks/uncertainty.md, ninth round, trajectory).

    Args:
        cov_model: (P, P) model covariance s^2 (J^T W J)^-1.
        jac_w: (n, P) Jacobian of the weighted residuals sqrt(w) (model - range), 0 on padding;
            res_w: (n,) those residuals.
        mask: (n,) valid entries, in time order (padding after them).
        n_clusters: number of consecutive stretches (static), or of clusters when `cluster` is given.
        cluster: (n,) int cluster of each entry in [0, n_clusters) (padding: n_clusters), e.g. the route
            cells of `cell_labels`; None = consecutive stretches. Empty clusters count for nothing.

    Returns:
        (P, P) symmetric PSD covariance >= both cov_model and the jackknife (the model alone where the
        jackknife is not finite).
    """
    if cluster is None:
        n_valid = jnp.maximum(jnp.sum(mask), 1)
        rank = jnp.cumsum(mask) - 1
        cluster = jnp.where(mask, (rank * n_clusters) // n_valid, n_clusters)
    n_used = jnp.sum(jax.ops.segment_sum(mask.astype(jac_w.dtype), cluster, n_clusters + 1)[:n_clusters] > 0)
    n_used = jnp.maximum(n_used.astype(jac_w.dtype), 1.0)
    jm = jnp.where(mask[:, None], jac_w, 0.0)
    s = jax.ops.segment_sum(jm * jnp.where(mask, res_w, 0.0)[:, None], cluster, n_clusters + 1)[:n_clusters]
    a_g = jax.ops.segment_sum(jm[:, :, None] * jm[:, None, :], cluster, n_clusters + 1)[:n_clusters]
    step = _leave_one_out_steps(jm.T @ jm, a_g, s)  # (G, P)
    jack = (n_used - 1.0) / n_used * step.T @ step
    jack = jnp.where(jnp.isfinite(jack).all(), jack, 0.0)
    d = 0.5 * (jack + jack.T) - 0.5 * (cov_model + cov_model.T)
    lam, vec = jnp.linalg.eigh(d)
    out = 0.5 * (cov_model + cov_model.T) + (vec * jnp.maximum(lam, 0.0)) @ vec.T
    return 0.5 * (out + out.T)


def _leave_one_out_steps(a, a_g, s, max_leverage: float = MAX_LEVERAGE):
    """The leave-one-stretch-out Gauss-Newton steps (A - A_g')^-1 s_g (G, P), with each stretch's leverage
    capped: A_g' is A_g with its generalized eigenvalues against A (the share of a direction's information
    that the stretch holds, in [0, 1]) clipped to `max_leverage`.

    Without the cap a stretch that holds almost all of one direction's information (leverage -> 1) gives
    that direction a near-infinite step, and the whole covariance follows from one nearly singular solve.
    Whitening by A (W^T A W = I) turns the generalized problem into an ordinary one: M_g = W^T A_g W =
    V diag(mu) V^T, and (A - A_g')^-1 = W V diag(1 / (1 - min(mu, cap))) V^T W^T.

    Args:
        a: (P, P) J^T W J. a_g: (G, P, P) its parts per stretch. s: (G, P) the stretches' scores.
    """
    lam, u = jnp.linalg.eigh(0.5 * (a + a.T))
    lam = jnp.maximum(lam, 1e-12 * jnp.maximum(jnp.sum(jnp.abs(lam)), jnp.finfo(lam.dtype).tiny))
    w = u / jnp.sqrt(lam)  # W: W^T A W = I

    def one(ag, sg):
        mu, v = jnp.linalg.eigh(w.T @ (0.5 * (ag + ag.T)) @ w)
        gain = 1.0 / (1.0 - jnp.clip(mu, 0.0, max_leverage))
        return w @ (v @ (gain * (v.T @ (w.T @ sg))))

    return jax.vmap(one)(a_g, s)


@eqx.filter_jit
def _solve_all(pos, rng, mask, p: NLSParams, with_cov: bool = True):
    """All anchors at once: `ls` initialisation, then `solve_anchor` (vmap); `p` and `with_cov` are static."""

    def one(ps, r, m):
        init, _ = multilaterate(ps, r, m, p.planar_tol_m, p.side, p.planar_ratio)
        init = jnp.where(jnp.isfinite(init), init, 0.0)
        return solve_anchor(ps, r, m, init, p, with_cov)

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
    if p.drift_model not in MODELS:
        raise JaxcalError(f"parameter drift_model: expected one of {', '.join(MODELS)}, got {p.drift_model!r}")
    if not p.cov_cell_m >= 0:
        raise JaxcalError(
            f"parameter cov_cell_m: must be a number >= 0 [m] (0 = cells from cov_cells), got {p.cov_cell_m}"
        )
    if not (isinstance(p.cov_sectors, int | np.integer) and p.cov_sectors >= 0):
        raise JaxcalError(f"parameter cov_sectors: must be an integer >= 0 (0 = none), got {p.cov_sectors}")
    if not 0 <= p.cov_cells < np.inf:
        raise JaxcalError(
            f"parameter cov_cells: must be a number >= 0 (cells along the route's box; 0 = none), got {p.cov_cells}"
        )
    # the route cells and the drift estimate enter only the covariances below: the fit runs with their defaults,
    # so a change of them reuses its compiled programs (they are static fields of `p`)
    fit_p = eqx.tree_at(
        lambda q: (q.cov_cell_m, q.cov_cells, q.cov_sectors, q.estimate_drift, q.drift_model),
        p,
        (
            NLSParams.cov_cell_m,
            NLSParams.cov_cells,
            NLSParams.cov_sectors,
            NLSParams.estimate_drift,
            NLSParams.drift_model,
        ),
    )
    groups, info = prepare_offset(dataset, fit_p)

    (est, cov, bias, codes), codes, steps = solve_all_checked(groups, fit_p)
    cov = cell_covariances(groups, np.asarray(est), np.asarray(bias), np.asarray(cov), p)
    info = dict(info, bias_m=[float(b) for b in bias])
    hint = f"raise max_steps (now {p.max_steps}; retried with {steps}) or n_irls (now {p.n_irls})"
    rep = report_fits("nls", codes, groups, p, hint)
    p, extra, pose_cov = drift_for_covariance(dataset, groups, est, bias, cov, p, "nls")
    return finish(dataset, "nls", p, groups, est, cov, dict(info, **extra), rep, pose_cov)


def solve_all_checked(groups, p: NLSParams, factor: int = 4, with_cov: bool = True):
    """`_solve_all` on prepared `groups`, once more with `factor` x `max_steps` for the anchors whose fit ran out
    of steps (`jaxcal.solver.retry_unconverged`, restricted to those anchors: every anchor's fit is independent,
    and a batched fit costs every anchor's steps until the slowest stops, so retrying all of them made one
    slow anchor cost the whole batch 4x). `with_cov` False: NaN covariances (`solve_anchor`; a start fit).
    Returns ((position, covariance, bias, codes), codes, steps used)."""
    out = _solve_all(groups.position, groups.range, groups.mask, p, with_cov)
    redo = np.flatnonzero(np.asarray(out[3]) == S.MAX_STEPS)
    if redo.size == 0 or factor <= 1:
        return out, out[3], p.max_steps
    steps = p.max_steps * factor
    sub = _solve_all(
        groups.position[redo],
        groups.range[redo],
        groups.mask[redo],
        eqx.tree_at(lambda q: q.max_steps, p, steps),
        with_cov,
    )
    out = tuple(jnp.asarray(full).at[redo].set(part) for full, part in zip(out, sub, strict=True))
    return out, out[3], steps


def prepare_offset(dataset, p: TrajectoryParams, start_per_anchor: int = START_PER_ANCHOR):
    """`prepare_poses` at the stated `time_offset_s`; with `estimate_offset`, the clock offset is first fitted
    jointly with the anchors from `nls`'s fit at the stated offset (`jaxcal.trajectory.offset.estimate`, one line
    with the estimate and its standard deviation or why it is NaN) and the poses are prepared at the offset
    applied. The front end of every trajectory method (`ls`, `nls`, `gp`).

    The start fit only seeds the joint fit, which refits every anchor and bias on its own subsample (2000 ranges
    per anchor, `offset.estimate`), so it runs on at most `start_per_anchor` ranges per anchor, evenly spaced
    (0 = all: the reference `tests/test_offset.py` compares with; on cuhksz, 38 000 ranges per anchor, the full
    start fit was as long as the method's own fit).

    Returns:
        (AnchorRanges, info): info as `prepare_poses`'s (`time_offset_s` the offset applied) and, with
        `estimate_offset`, `time_offset_estimate_s`, `time_offset_sd_s` (NaN where not identifiable) and
        `offset_sensitivity` ((A, 3) d anchor / d offset [m/s]; `finish` adds the offset's variance with it),
        `time_offset_rounds` (the joint fit's rounds) and `time_offset_stretch_p` (Cochran Q's p-value). A stated
        `pose_sd_m` / `pose_drift` widens the offset's sd.
    """
    fixed = eqx.tree_at(lambda q: q.estimate_offset, p, False)
    if not p.estimate_offset:
        return prepare_poses(dataset, fixed)
    start, _ = prepare(
        dataset, p.order, p.knot_dt_s, p.max_gap_s, p.time_offset_s, max_per_anchor=int(start_per_anchor)
    )
    shared = {k: getattr(p, k) for k in ("min_ranges", "planar_tol_m", "planar_ratio", "side")}
    p_nls = p if isinstance(p, NLSParams) else with_overrides(NLSParams(), shared)
    # the start needs no covariance: a program without the jackknifes compiles in about a third of the time
    (est, _, bias, _), _, _ = solve_all_checked(start, p_nls, with_cov=False)
    model = fit_poses(dataset, p.order, p.knot_dt_s, p.max_gap_s)
    pose = {"pose_sd_m": p.pose_sd_m, "pose_drift": p.pose_drift, "pose_t0": float(np.asarray(dataset.pose_time)[0])}
    fit = estimate_offset_fit(
        model, dataset, np.asarray(est), np.asarray(bias), p.time_offset_s, p.max_offset_s, **pose
    )
    logging.getLogger("jaxcal").warning("%s", summary(fit, p.time_offset_s))
    extra: dict = {
        "time_offset_estimate_s": fit.offset_s,
        "time_offset_sd_s": fit.sd_s,
        "time_offset_rounds": fit.rounds,
        "time_offset_stretch_p": fit.stretch_p,
    }
    applied = p.time_offset_s
    if np.isfinite(fit.offset_s):
        applied = fit.offset_s
        extra["offset_sensitivity"] = fit.sensitivity.tolist()
    groups, info = prepare_poses(dataset, eqx.tree_at(lambda q: q.time_offset_s, fixed, applied))
    return groups, dict(info, **extra)
