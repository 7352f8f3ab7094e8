"""The shape of the path as one anchor sees it, where it hides part of the anchor's position whatever the data.

Ranges from a path that is symmetric about a line or a plane are the same from an anchor and from its image
under that symmetry: no fit, however many ranges, can tell the two apart. Two shapes are not the nearly
horizontal plane that `common.unobservable_height` and the mirror check (`jaxcal.trajectory.mirror`) handle
with the convention that anchors are above the path (`side`):

- **a line** (the tag positions within `planar_tol_m` of a straight line: a straight, flat corridor or road):
  the ranges depend only on the anchor's position along the line and its distance from it, and every point of
  the circle about the line fits alike. Before this module the fits put such an anchor straight above the path
  at that distance, with centimetre standard deviations, 4-7 m from the truth (a straight 160 m road, anchors
  4-8 m beside it). `fit_line` fits (position along, distance from, range bias) instead; `line_anchors` keeps
  the coordinates that the circle does not move by more than `mirror_min_sep_m` and leaves the others NaN.
- **a steep plane** (the smallest spread below `planar_tol_m` or `planar_ratio` x the in-plane spread, the plane
  steeper than 60 degrees: a straight road over hills): the mirror image through the plane fits alike, and no
  convention picks the side: across a vertical plane there is no above. The height test counted such a path as
  flat (its height spread is small against its length), so the side came from the convention, and the fit,
  started in the plane, stayed there (a saddle of the symmetric cost): 5-8 m off for 0.1-0.4 m predicted.
  These anchors now get the mirror check (`compare_sides`) from a start off the plane (`plane_start`), which
  leaves the coordinates that differ between the two sides NaN when the ranges cannot tell them apart.

`shapes` classifies every anchor by the principal axes of its tag positions (all of them, unweighted: one range
off the plane breaks the symmetry, weakly, and the mirror check's likelihood-ratio test weighs that).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.optimize import least_squares

from jaxcal.trajectory.common import cauchy_weights
from jaxcal.trajectory.nls import NLSParams, route_cells
from jaxcal.trajectory.systematic import place_variance

__all__ = ["PathShape", "shapes", "plane_start", "steep_starts", "fit_line", "LineFit", "line_anchors"]

STEEP_NZ = 0.5
"""A plane whose unit normal has |n_z| below this (steeper than 60 degrees) is steep: no `side` convention."""


class PathShape(NamedTuple):
    """Per anchor (A = anchors): `line` and `steep` (A,) bool; `centre` (A, 3) [m], the mean tag position;
    `axis` (A, 3) the direction of largest spread; `normal` (A, 3) that of the smallest; `spread` (A, 3) [m] the
    standard deviations along the principal axes, largest first (NaN rows: fewer than 4 ranges)."""

    line: np.ndarray
    steep: np.ndarray
    centre: np.ndarray
    axis: np.ndarray
    normal: np.ndarray
    spread: np.ndarray


def shapes(groups, p) -> PathShape:
    """`PathShape` of every anchor's tag positions (module doc), with `p.planar_tol_m` and `p.planar_ratio`."""
    pos, mask = np.asarray(groups.position), np.asarray(groups.mask)
    a_n = pos.shape[0]
    out = PathShape(
        line=np.zeros(a_n, bool),
        steep=np.zeros(a_n, bool),
        centre=np.full((a_n, 3), np.nan),
        axis=np.full((a_n, 3), np.nan),
        normal=np.full((a_n, 3), np.nan),
        spread=np.full((a_n, 3), np.nan),
    )
    for a in range(a_n):
        q = pos[a][mask[a]]
        if q.shape[0] < 4:
            continue
        c = q.mean(axis=0)
        lam, vec = np.linalg.eigh((q - c).T @ (q - c) / q.shape[0])
        s = np.sqrt(np.maximum(lam[::-1], 0.0))  # largest first
        out.centre[a], out.axis[a], out.normal[a], out.spread[a] = c, vec[:, 2], vec[:, 0], s
        out.line[a] = s[1] < p.planar_tol_m
        thin = (s[2] < p.planar_tol_m) | (s[2] < p.planar_ratio * np.hypot(s[0], s[1]))
        out.steep[a] = bool(thin and abs(vec[2, 0]) < STEEP_NZ and not out.line[a])
    return out


def plane_start(q: np.ndarray, r: np.ndarray, centre: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(3,) a start off the plane (`centre`, unit `normal`) of tag positions `q` (n, 3) for ranges `r` (n,) [m]:
    the linear multilateration in the plane's frame (in-plane a_1, a_2 and a_1^2 + a_2^2 + u^2 from
    r^2 - |t|^2 = -2 a.t + |a|^2, the tags' offsets from the plane neglected), at +u along `normal`."""
    e1 = np.cross(normal, [0.0, 0.0, 1.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(normal, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    t = np.column_stack([(q - centre) @ e1, (q - centre) @ e2])
    a_mat = np.column_stack([-2.0 * t, np.ones(len(r))])
    x, *_ = np.linalg.lstsq(a_mat, r**2 - np.sum(t**2, axis=1), rcond=None)
    u = np.sqrt(max(x[2] - x[0] ** 2 - x[1] ** 2, 1.0))
    return centre + x[0] * e1 + x[1] * e2 + u * normal


class LineFit(NamedTuple):
    """`fit_line`'s answer: along [m] (from the centre, along the axis), its variance var_along [m^2], the
    distance from the line rho [m] and the range bias [m]."""

    along: float
    var_along: float
    rho: float
    bias: float


def fit_line(q: np.ndarray, r: np.ndarray, centre: np.ndarray, axis: np.ndarray, cells: np.ndarray) -> LineFit:
    """Fit r = sqrt((s - tau)^2 + rho^2) + b + e to ranges `r` (n,) from tag positions `q` (n, 3) on a line
    (`centre`, unit `axis`; tau the tags' positions along it), Cauchy loss at nls's scale (scipy's
    `least_squares`: three parameters, one anchor at a time; not worth a compiled program).

    The variance of s is the largest of the fit's own (Cauchy IRLS weights, residual variance), the sandwich
    over 16 consecutive stretches of ranges and the place-to-place term of `jaxcal.trajectory.systematic`
    (the between-cell variance of the residuals in the route `cells` (n,), times the dilution of precision of s)."""
    tau = (q - centre) @ axis
    off = np.linalg.norm(q - centre - tau[:, None] * axis, axis=1)
    k = int(np.argmin(r))
    x0 = np.array([tau[k], max(float(np.sqrt(max(r[k] ** 2 - off[k] ** 2, 0.0))), 0.5), 0.0])

    def residual(x):
        return np.sqrt((x[0] - tau) ** 2 + x[1] ** 2 + off**2) + x[2] - r

    res0 = residual(x0)
    scale = max(2.385 * 1.4826 * float(np.median(np.abs(res0 - np.median(res0)))), 0.05)
    sol = least_squares(residual, x0, loss="cauchy", f_scale=scale, x_scale="jac")
    s, rho, b = sol.x
    res = residual(sol.x)
    w = cauchy_weights(res - np.median(res))
    d = np.sqrt((s - tau) ** 2 + rho**2 + off**2)
    h = np.column_stack([(s - tau) / d, rho / d, np.ones_like(d)])
    info = (h * w[:, None]).T @ h
    inv = np.linalg.pinv(info, hermitian=True)
    sigma2 = float(np.sum(w * res**2) / max(np.sum(w) - 3.0, 1.0))
    score = h * (w * res)[:, None]
    g = 16
    chunks = np.array_split(np.arange(len(r)), g)
    sums = np.array([score[c].sum(axis=0) for c in chunks if c.size])
    meat = sums.shape[0] / max(sums.shape[0] - 1.0, 1.0) * (sums - sums.mean(axis=0)).T @ (sums - sums.mean(axis=0))
    sandwich = inv @ meat @ inv
    place = place_variance(res - np.median(res), w, cells) * inv[0, 0] * float(np.sum(w))
    return LineFit(float(s), float(max(sigma2 * inv[0, 0], sandwich[0, 0], place)), float(abs(rho)), float(b))


def steep_starts(est: np.ndarray, steep: np.ndarray, todo: np.ndarray, data: tuple, shape):
    """(`est` with the rows of steep anchors in `todo` whose estimate lies in the plane of their path (less than
    half as far from it as `path_shape.plane_start`'s start, or in it: a saddle of the symmetric cost that a fit
    started there does not leave) replaced by that start, (A,) bool: replaced)."""
    start = np.array(est, dtype=float)
    replaced = np.zeros(est.shape[0], bool)
    pos, rng, mask = data
    for a in todo[steep[todo]]:
        m = mask[a]
        ps = plane_start(pos[a][m], rng[a][m], shape.centre[a], shape.normal[a])
        u_ps = float((ps - shape.centre[a]) @ shape.normal[a])
        if abs(float((est[a] - shape.centre[a]) @ shape.normal[a])) < 0.5 * abs(u_ps):
            start[a], replaced[a] = ps, True
    return start, replaced


def line_anchors(groups, est: np.ndarray, cov: np.ndarray, shape, pose_cov: np.ndarray, p) -> dict:
    """In place on `est` and `cov`: every anchor whose path is a line (`shape.line`, `path_shape`) gets
    `path_shape.fit_line`'s answer: the coordinates that the circle about the line moves by more than
    `p.mirror_min_sep_m` NaN, the rest at the position along the line, with variance
    axis_i^2 var(along) + rho^2 (1 - axis_i^2) / 2 (the circle's spread in that coordinate) + the pose error.
    Returns {anchor index: {"along_m", "along_sd_m", "from_line_m", "centre", "axis"}} (JSON-ready)."""
    out: dict[int, dict] = {}
    todo = np.flatnonzero(shape.line & np.isfinite(est).any(axis=1))
    if todo.size == 0:
        return out
    pos, rng, mask = np.asarray(groups.position), np.asarray(groups.range), np.asarray(groups.mask)
    cells, _ = route_cells(groups, NLSParams())
    for a in todo:
        m = mask[a]
        c, e = shape.centre[a], shape.axis[a]
        f = fit_line(pos[a][m], rng[a][m], c, e, cells[a][m])
        moves = f.rho * np.sqrt(np.maximum(1.0 - e**2, 0.0))
        keep = moves <= p.mirror_min_sep_m
        var = e**2 * f.var_along + 0.5 * moves**2 + np.diag(pose_cov[a])
        est[a] = np.where(keep, c + f.along * e, np.nan)
        cov[a] = np.where(np.outer(keep, keep), np.diag(np.where(keep, var, 0.0)), np.nan)
        out[int(a)] = {
            "along_m": round(f.along, 3),
            "along_sd_m": round(float(np.sqrt(f.var_along)), 3),
            "from_line_m": round(f.rho, 3),
            "centre": [round(float(v), 3) for v in c],
            "axis": [round(float(v), 4) for v in e],
        }
    return out
