"""The part of the range error that is the same wherever the platform is in the same place, as one error.

A trajectory fit sees thousands of ranges. Counted as independent, they shrink an anchor's covariance to
centimetres, and the cluster jackknifes (`jaxcal.trajectory.nls`) still treat each route cell as independent of
the others. Errors tied to the scene are not: a building puts the same NLOS excess (the channel's NLOS core lies
0.4 m above the LOS one) on every range from the tens of cells behind it, on every pass. Along a direction the
path fixes well such an error moves the fit little, but along one it fixes poorly (the rotation about a straight
road, the height above a gently rolling one) the fit follows it by metres: on the simulated campus family the
anchors outside their 95 % ellipse were off along exactly those directions (docs/benchmarks/uncertainty.md,
nineteenth to twenty-first rounds).

`systematic_covariances` sizes that error from the data and propagates it as one error, GNSS-style (position
error = dilution of precision x range error):

- s_b^2, the place-to-place variance of the range residuals: the weighted variance of the route cells' mean
  residuals (`nls.route_cells`, Cauchy weights about the median residual) less the part that the ranges' own
  noise gives each cell mean (a variance-components estimate, so that clean ranges in many small cells do not
  count as a systematic error);
- D = (H^T W H / sum W)^-1, the dilution of precision of the anchor's ranges for (position, range bias), H the
  rows (unit vector from the tag to the anchor, 1);
- the covariance s_b^2 D, as if all those cell errors were one range error of that size: no averaging over
  cells, passes or ranges. For an anchor whose height the path cannot observe (`common.unobservable_height`)
  the horizontal block is the marginal over the height (the Schur complement), the height rows zero (NaN later).

A fit can absorb its own place errors. Where the ranges that fix a direction are those that carry the error (an
anchor beside a straight road: only the ranges from the other roads, seen through the buildings, fix its rotation
about the road), the fit moves along that direction until the residuals no longer show the error. On the simulated
campus the anchors outside their ellipse had s_b 0.02-0.06 m from their residuals where the true range errors of
the same cells had 0.15-0.20 m (twenty-third round, docs/benchmarks/uncertainty.md). The residuals cannot tell such
an anchor from a clean one; the other anchors of the campaign can: the same platform and radio see the same kind of
site through each of them. So each anchor's s_b^2 is at least the campaign's `site_variance`, the median of the
anchors' own (`pool`; `TrajectoryParams.systematic_pool`).

`common.finish` widens every method's covariance to it (in every direction where it is smaller; pose and clock
errors are then added as before).
"""

from __future__ import annotations

import numpy as np

from jaxcal.trajectory.common import cauchy_weights
from jaxcal.trajectory.nls import NLSParams, route_cells

__all__ = ["place_variance", "dilution", "place_variances", "site_variance", "systematic_covariances"]


def place_variance(res: np.ndarray, w: np.ndarray, cells: np.ndarray) -> float:
    """Between-cell variance component [m^2] of residuals `res` with weights `w` in cells `cells` (ints >= 0):
    the `w`-weighted variance of the cells' weighted mean residuals (each cell weighted by its total weight)
    less the weighted mean of each cell mean's own sampling variance sum(w^2 (e - m)^2) / (sum w)^2; >= 0."""
    res, w, cells = np.asarray(res, float), np.asarray(w, float), np.asarray(cells)
    _, c = np.unique(cells, return_inverse=True)
    c = c.ravel()
    wc = np.bincount(c, weights=w)
    keep = wc > 0
    if keep.sum() < 2:
        return 0.0
    mean = np.bincount(c, weights=w * res) / np.where(keep, wc, 1.0)
    noise = np.bincount(c, weights=w**2 * (res - mean[c]) ** 2)[keep] / wc[keep] ** 2
    mean, wk = mean[keep], wc[keep]
    between = np.average(mean**2, weights=wk) - np.average(mean, weights=wk) ** 2 - np.average(noise, weights=wk)
    return float(max(between, 0.0))


def dilution(pos: np.ndarray, anchor: np.ndarray, w: np.ndarray, height: bool = True) -> np.ndarray:
    """(3, 3) position block of D = (H^T W H / sum W)^-1 for ranges from tag positions `pos` (n, 3) to `anchor` (3,)
    with weights `w` (n,), H the rows (unit vector from the tag to the anchor, 1). `height` False: the horizontal
    block of the marginal over the height (the Schur complement of the height in H^T W H), the height rows 0."""
    d = anchor[None] - pos
    r = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
    h = np.column_stack([d / r[:, None], np.ones_like(r)])
    info = (h * w[:, None]).T @ h / max(float(np.sum(w)), 1e-300)
    out = np.zeros((3, 3))
    if height:
        out[:] = np.linalg.pinv(info, hermitian=True)[:3, :3]
        return out
    keep = [0, 1, 3]
    a = info[np.ix_(keep, keep)]
    if info[2, 2] > 1e-12 * np.trace(info):
        a = a - np.outer(info[keep, 2], info[2, keep]) / info[2, 2]
    out[:2, :2] = np.linalg.pinv(a, hermitian=True)[:2, :2]
    return out


def _anchor_terms(groups, est: np.ndarray, flat: np.ndarray | None):
    """Per anchor with a finite fit and >= 4 ranges: (anchor, s_b^2, (tag positions, Cauchy weights, height
    observable)), the last three what `dilution` takes (module doc)."""
    est = np.asarray(est, dtype=float)
    pos_all, rng_all, mask_all = np.asarray(groups.position), np.asarray(groups.range), np.asarray(groups.mask)
    labels, _ = route_cells(groups, NLSParams())
    for a in range(est.shape[0]):
        m = mask_all[a]
        if m.sum() < 4 or not np.isfinite(est[a]).all():
            continue
        pos, rng = pos_all[a][m], rng_all[a][m]
        res = np.linalg.norm(pos - est[a], axis=1) - rng
        res = res - np.median(res)
        w = cauchy_weights(res)
        height = True if flat is None else not bool(flat[a])
        yield a, place_variance(res, w, labels[a][m]), (pos, w, height)


def place_variances(groups, est: np.ndarray) -> np.ndarray:
    """(A,) each anchor's place-to-place variance s_b^2 [m^2] at its fit `est` (A, 3) (module doc); NaN for anchors
    without a finite fit or with fewer than 4 ranges."""
    out = np.full(np.asarray(est).shape[0], np.nan)
    for a, s2, _ in _anchor_terms(groups, est, None):
        out[a] = s2
    return out


def site_variance(s2: np.ndarray) -> float:
    """The campaign's place-to-place variance [m^2]: the median of the anchors' `place_variances` (NaN ones left
    out; 0 where there are none). The median, not the mean or the largest: one anchor whose ranges cross a whole
    building does not set every other anchor's floor."""
    s2 = np.asarray(s2, dtype=float)
    s2 = s2[np.isfinite(s2)]
    return float(np.median(s2)) if s2.size else 0.0


def systematic_covariances(groups, est: np.ndarray, flat: np.ndarray | None = None, pool: float = 0.0) -> np.ndarray:
    """(A, 3, 3) covariance of each anchor's fit `est` (A, 3) from the place-to-place part of its range errors
    taken as one error (module doc): max(s_b^2, pool) D. Zeros for anchors without a finite fit or with fewer than
    4 ranges. `flat` ((A,) bool or None): anchors whose height the path cannot observe (marginal horizontal block).
    `pool` [m^2]: the campaign's `site_variance` (0: each anchor's own s_b^2 alone).

    Args:
        groups: the prepared ranges (`jaxcal.trajectory.poses.AnchorRanges`: position (A, n, 3), range and mask
            (A, n)); route cells are nls's (`nls.route_cells` with `NLSParams` defaults), whatever the method.
    """
    est = np.asarray(est, dtype=float)
    out = np.zeros((est.shape[0], 3, 3))
    for a, s2, (pos, w, height) in _anchor_terms(groups, est, flat):
        out[a] = max(s2, pool) * dilution(pos, est[a], w, height)
    return out
