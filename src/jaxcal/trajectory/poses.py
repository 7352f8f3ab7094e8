"""Tag positions at range time (paper 001, Sec. III-B) and per-anchor grouping of the ranges.

Positions come from a cumulative cubic B-spline fitted to the pose stream (`bspline.py`); orientations
are interpolated by slerp between the two neighbouring poses. Between two consecutive poses with
identical positions the platform is taken as standing still (exact position, no spline ringing)
(the paper omits R(t) in the calibration;
we need it only to rotate each tag's lever arm into the world frame). Ranges outside the pose time
span, or inside a gap of the pose stream longer than `max_gap_s`, are dropped and counted.

An optional constant clock offset between the range and pose clocks (`t_pose = t_range + offset`) is
estimated by a 1-D search that minimises the median absolute residual of a linear least-squares
multilateration of every anchor (`estimate_time_offset`): a coarse grid over [-max, max], then a finer
grid around the best value. Wrong offsets smear the tag positions along the path and inflate the
residuals; on static recordings the objective is flat and the search returns about zero.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from jaxcal.precision import in_float64
from jaxcal.shapes import padded_length
from jaxcal.trajectory import bspline
from jaxcal.trajectory.common import TrajectoryParams, multilaterate_all
from jaxcal.trajectory.offset import estimate

__all__ = [
    "AnchorRanges",
    "quat_rotate",
    "slerp_orientation",
    "PoseModel",
    "fit_poses",
    "tag_positions",
    "group_by_anchor",
    "estimate_time_offset",
    "estimate_offset_fit",
    "prepare",
    "prepare_poses",
]


class AnchorRanges(eqx.Module):
    """Ranges grouped per anchor, padded to a common length (so that methods vmap over anchors).

    Attributes:
        position: (A, n, 3) tag positions in the world frame [m] at range time.
        range: (A, n) measured ranges [m].
        mask: (A, n) True for real entries, False for padding.
        time: (A, n) range times [s] (0 on padding), or None where the grouping did not keep them.
    """

    position: Float[Array, "a n 3"]
    range: Float[Array, "a n"]
    mask: Bool[Array, "a n"]
    time: Float[Array, "a n"] | None = None


def quat_rotate(q: Float[Array, "... 4"], v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """Rotate vectors `v` by unit quaternions `q` (x, y, z, w; scalar last)."""
    u, w = q[..., :3], q[..., 3:4]
    t = 2.0 * jnp.cross(u, v)
    return v + w * t + jnp.cross(u, t)


def slerp_orientation(
    pose_time: Float[Array, " p"], quat: Float[Array, "p 4"], time_s: Float[Array, " r"]
) -> Float[Array, "r 4"]:
    """Orientation at `time_s` by slerp between the neighbouring poses (x, y, z, w quaternions)."""
    n = pose_time.shape[0]
    i = jnp.clip(jnp.searchsorted(pose_time, time_s, side="right") - 1, 0, n - 2)
    ta, tb = pose_time[i], pose_time[i + 1]
    s = jnp.clip((time_s - ta) / (tb - ta), 0.0, 1.0)[:, None]
    qa, qb = quat[i], quat[i + 1]
    dot = jnp.sum(qa * qb, axis=-1, keepdims=True)
    qb = jnp.where(dot < 0, -qb, qb)  # shortest arc
    dot = jnp.abs(dot)
    theta = jnp.arccos(jnp.clip(dot, -1.0, 1.0))
    sin_t = jnp.sin(theta)
    small = sin_t < 1e-6
    safe = jnp.where(small, 1.0, sin_t)
    wa = jnp.where(small, 1.0 - s, jnp.sin((1.0 - s) * theta) / safe)
    wb = jnp.where(small, s, jnp.sin(s * theta) / safe)
    q = wa * qa + wb * qb
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


class PoseModel(eqx.Module):
    """Continuous-time pose stream: spline positions plus the raw orientations for slerp.

    Attributes:
        spline: fitted B-spline pieces of the positions.
        pose_time: (P,) [s]. position: (P, 3) [m]. orientation: (P, 4) unit quaternions (x, y, z, w).
    """

    spline: bspline.SplinePieces
    pose_time: Float[Array, " p"]
    position: Float[Array, "p 3"]
    orientation: Float[Array, "p 4"]


def fit_poses(ds, order: int = 4, knot_dt_s: float = 0.0, max_gap_s: float = 0.0) -> PoseModel:
    """Fit the continuous-time pose model of a TrajectoryDataset (host side).

    Args:
        ds: TrajectoryDataset.
        order: B-spline order (4 = cubic).
        knot_dt_s: knot spacing [s]; 0 = median pose interval.
        max_gap_s: pose gaps longer than this split the spline; 0 = 5 x knot spacing.
    """
    spline = bspline.fit_pieces(ds.pose_time, ds.pose_position, order, knot_dt_s, max_gap_s)
    q = ds.pose_orientation
    if q is None:
        q = np.tile(np.array([0.0, 0.0, 0.0, 1.0]), (ds.pose_time.shape[0], 1))
    return PoseModel(spline, jnp.asarray(ds.pose_time), jnp.asarray(ds.pose_position), jnp.asarray(q))


def tag_positions(
    model: PoseModel,
    lever_arm: Float[Array, "t 3"],
    range_time: Float[Array, " r"],
    range_tag: Array,
    offset_s: Float[Array, ""] | float = 0.0,
) -> Float[Array, "r 3"]:
    """World positions [m] of the ranging tag at each range time (traceable); NaN outside the poses.

    Args:
        model: pose model. lever_arm: (T, 3) tag antennas in the body frame [m].
        range_time: (R,) [s] on the range clock. range_tag: (R,) tag index.
        offset_s: pose clock minus range clock [s].
    """
    t = jnp.asarray(range_time) + offset_s
    p = bspline.evaluate(model.spline, t)
    # Between two poses at the same position the platform stands still (e.g. dwells at surveyed
    # points, two poses per dwell): take that position exactly rather than the spline, which rings
    # on such step-like streams.
    n = model.pose_time.shape[0]
    i = jnp.clip(jnp.searchsorted(model.pose_time, t, side="right") - 1, 0, n - 2)
    pa, pb = model.position[i], model.position[i + 1]
    static = jnp.all(pa == pb, axis=-1) & jnp.isfinite(p).all(axis=-1)
    p = jnp.where(static[:, None], pa, p)
    q = slerp_orientation(model.pose_time, model.orientation, t)
    return p + quat_rotate(q, jnp.asarray(lever_arm)[jnp.asarray(range_tag)])


def group_by_anchor(
    anchor: np.ndarray,
    position: np.ndarray,
    rng: np.ndarray,
    n_anchors: int,
    max_per_anchor: int = 0,
    seed: int = 0,
    time: np.ndarray | None = None,
) -> AnchorRanges:
    """Group valid ranges per anchor into padded arrays (host side).

    The arrays are padded (mask False) to `padded_length` of the largest anchor's count (inside
    `jaxcal.shapes.exact_lengths`: to that count), so that campaigns of similar size share one shape and a loop
    over them (a sweep, a family) reuses the compiled programs instead of compiling every fit again; every
    consumer reads the mask.

    Args:
        anchor: (R,) anchor index. position: (R, 3) tag positions [m] (NaN rows are dropped).
        rng: (R,) ranges [m] (NaN dropped). n_anchors: A.
        max_per_anchor: keep at most this many ranges per anchor, drawn evenly spaced in time
            (0 = all); used only to bound memory on very long recordings.
        seed: unused unless subsampling needs ties broken (kept for reproducibility).
        time: (R,) range times [s], kept per anchor in `AnchorRanges.time` (None: not kept).
    """
    anchor = np.asarray(anchor)
    position = np.asarray(position, dtype=float)
    rng = np.asarray(rng, dtype=float)
    ok = np.isfinite(position).all(axis=1) & np.isfinite(rng)
    groups = []
    for a in range(n_anchors):
        idx = np.nonzero(ok & (anchor == a))[0]
        if max_per_anchor and idx.size > max_per_anchor:
            idx = idx[np.linspace(0, idx.size - 1, max_per_anchor).round().astype(int)]
        groups.append(idx)
    n = padded_length(max(1, max(g.size for g in groups)))
    pos = np.zeros((n_anchors, n, 3))
    r = np.zeros((n_anchors, n))
    m = np.zeros((n_anchors, n), dtype=bool)
    t = np.zeros((n_anchors, n))
    for a, g in enumerate(groups):
        pos[a, : g.size] = position[g]
        r[a, : g.size] = rng[g]
        m[a, : g.size] = True
        if time is not None:
            t[a, : g.size] = np.asarray(time, dtype=float)[g]
    return AnchorRanges(jnp.asarray(pos), jnp.asarray(r), jnp.asarray(m), None if time is None else jnp.asarray(t))


def _offset_objective(model, lever_arm, range_time, range_tag, range_anchor, rng, n_anchors, n_per, offset):
    p = tag_positions(model, lever_arm, range_time, range_tag, offset)
    valid = jnp.isfinite(p).all(axis=1) & jnp.isfinite(rng)
    # Fixed-size per-anchor gather (static n_per) so that the objective is one traced function.
    order = jnp.argsort(jnp.where(valid, range_anchor, n_anchors), stable=True)
    sorted_anchor = jnp.where(valid, range_anchor, n_anchors)[order]
    start = jnp.searchsorted(sorted_anchor, jnp.arange(n_anchors))
    count = jnp.searchsorted(sorted_anchor, jnp.arange(n_anchors), side="right") - start
    j = jnp.arange(n_per)
    take = start[:, None] + jnp.minimum(j[None, :], jnp.maximum(count[:, None] - 1, 0))
    idx = order[jnp.clip(take, 0, order.shape[0] - 1)]
    mask = j[None, :] < count[:, None]
    pos = jnp.where(mask[..., None], jnp.nan_to_num(p[idx]), 0.0)
    rr = jnp.where(mask, jnp.nan_to_num(rng[idx]), 0.0)
    est, _ = multilaterate_all(pos, rr, mask)
    res = jnp.abs(jnp.linalg.norm(pos - est[:, None, :], axis=-1) - rr)
    res = jnp.where(mask & jnp.isfinite(est).all(axis=1)[:, None], res, jnp.nan)
    # Median absolute residual, but only over anchors with enough ranges; also the fraction kept,
    # so that an offset that pushes ranges out of the pose span is not rewarded.
    return jnp.nanmedian(res)


def estimate_time_offset(
    model: PoseModel, ds, max_offset_s: float = 1.0, n_grid: int = 41, max_per_anchor: int = 2000
) -> float:
    """Constant clock offset [s] (pose clock minus range clock) by a coarse-to-fine 1-D search.

    Args:
        model: pose model. ds: TrajectoryDataset.
        max_offset_s: search interval [-max, max].
        n_grid: grid points per level (two levels: the second spans two coarse steps around the best).
        max_per_anchor: ranges per anchor used by the objective (evenly spaced subsample).

    Returns:
        The offset [s] minimising the median absolute multilateration residual.
    """
    r = np.asarray(ds.range, dtype=float)
    keep = np.isfinite(r)
    # Evenly spaced subsample per anchor (host side) to bound the cost of each objective evaluation.
    picked: list[np.ndarray] = []
    for a in range(ds.n_anchors):
        idx = np.nonzero(keep & (ds.range_anchor == a))[0]
        if idx.size > max_per_anchor:
            idx = idx[np.linspace(0, idx.size - 1, max_per_anchor).round().astype(int)]
        picked.append(idx)
    sel = np.sort(np.concatenate(picked))
    n_per = int(max(1, max((np.sum(ds.range_anchor[sel] == a) for a in range(ds.n_anchors)), default=1)))
    args = (
        model,
        jnp.asarray(ds.lever_arm),
        jnp.asarray(ds.range_time[sel]),
        jnp.asarray(ds.range_tag[sel]),
        jnp.asarray(ds.range_anchor[sel]),
        jnp.asarray(r[sel]),
    )

    @eqx.filter_jit
    def scan_grid(args, grid):
        return jax.lax.map(lambda o: _offset_objective(*args, ds.n_anchors, n_per, o), grid)

    grid = jnp.linspace(-max_offset_s, max_offset_s, n_grid)
    f = scan_grid(args, grid)
    best = float(grid[jnp.nanargmin(f)])
    step = 2.0 * max_offset_s / (n_grid - 1)
    fine = jnp.linspace(best - step, best + step, n_grid)
    f2 = scan_grid(args, fine)
    return float(fine[jnp.nanargmin(f2)])


def prepare(
    ds,
    order: int = 4,
    knot_dt_s: float = 0.0,
    max_gap_s: float = 0.0,
    time_offset_s: float = 0.0,
    estimate_offset: bool = False,
    max_offset_s: float = 1.0,
    max_per_anchor: int = 0,
) -> tuple[AnchorRanges, dict]:
    """Tag positions at range time, grouped per anchor; the common front end of every method.

    Args:
        ds: TrajectoryDataset.
        order, knot_dt_s, max_gap_s: B-spline settings (`fit_poses`).
        time_offset_s: pose clock minus range clock [s], used when `estimate_offset` is False.
        estimate_offset: estimate the offset by the grid search `estimate_time_offset` within +-`max_offset_s`
            (the methods instead estimate it jointly with the anchors: `jaxcal.trajectory.nls.prepare_offset`).
        max_per_anchor: cap of ranges per anchor (0 = all).

    Returns:
        (AnchorRanges, info) with info keys `time_offset_s`, `ranges_used`, `ranges_dropped`.
    """
    model = fit_poses(ds, order, knot_dt_s, max_gap_s)
    offset = float(time_offset_s)
    if estimate_offset:
        offset = estimate_time_offset(model, ds, max_offset_s)
    p = np.asarray(
        jax.jit(tag_positions)(
            model,
            jnp.asarray(ds.lever_arm),
            jnp.asarray(ds.range_time),
            jnp.asarray(ds.range_tag),
            offset,
        )
    )
    r = np.asarray(ds.range, dtype=float)
    ok = np.isfinite(p).all(axis=1) & np.isfinite(r)
    groups = group_by_anchor(ds.range_anchor, p, r, ds.n_anchors, max_per_anchor, time=ds.range_time)
    info = {
        "time_offset_s": offset,
        "ranges_used": int(ok.sum()),
        "ranges_dropped": int((~ok).sum()),
    }
    return groups, info


@in_float64
def estimate_offset_fit(
    model: PoseModel, ds, anchors, bias, start_s: float = 0.0, max_offset_s: float = 1.0, **options
):
    """The clock offset of `ds` with its standard deviation (`jaxcal.trajectory.offset.estimate`: from
    `start_s` [s] and the anchors (A, 3) [m] and range biases (A,) [m] fitted at it, within +-`max_offset_s`):
    an `OffsetFit`; `options` go to `estimate`."""
    pos_fn = jax.tree_util.Partial(tag_positions, model, jnp.asarray(ds.lever_arm))
    return estimate(
        pos_fn,
        ds.range_time,
        ds.range_tag,
        ds.range_anchor,
        ds.range,
        anchors,
        bias,
        start_s,
        max_offset_s,
        **options,
    )


def prepare_poses(dataset, p: TrajectoryParams) -> tuple[AnchorRanges, dict]:
    """`prepare` with the pose and clock settings of a trajectory method's parameters `p`."""
    return prepare(dataset, p.order, p.knot_dt_s, p.max_gap_s, p.time_offset_s, p.estimate_offset, p.max_offset_s)
