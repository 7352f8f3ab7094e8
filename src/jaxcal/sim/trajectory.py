"""Simulated trajectory scenarios: a vehicle with known (odometry) poses ranging to fixed anchors.

`campus` (after paper 001, 600 x 450 m): a road grid (4 east-west roads, 5 north-south roads) with
building blocks between them; 10 anchors on poles 4-8 m beside the roads, 3-6 m above the ground; a
vehicle drives a boustrophedon route over every road (so it passes every anchor) at 8 m/s on gently
rolling terrain (+-3.5 m). Poses at 10 Hz (position + heading quaternion), one tag on a roof mast
(lever arm (0.5, 0, 1.8) m); each anchor is ranged at 20 Hz (a tag round over all anchors) up to
`max_range_m` (120 m). A link is LOS unless the 2-D segment tag-anchor crosses a building block;
range errors come from `jaxcal.sim.channel` (LOS/NLOS mixture after Table I of paper 000).

Odometry drift (`drift`, [m / sqrt(s)]): the *reported* poses are the true ones plus an independent
horizontal random walk per axis with that standard deviation per sqrt(second) (Brownian motion,
z unaffected); the ranges are computed from the true poses, so drift is pose error the calibration
must absorb. `drift=0` gives exact poses.

Clock offset (`time_offset_s`): the reported poses are stamped on a clock that runs `time_offset_s` ahead
of the range clock (pose clock minus range clock), the error that `estimate_offset` of the trajectory
methods undoes.
"""

from __future__ import annotations

import numpy as np

from jaxcal.data import TrajectoryDataset
from jaxcal.errors import InputError
from jaxcal.sim.channel import ChannelModel, sample_range_errors

__all__ = ["SCENARIOS", "simulate", "campus_layout"]

SCENARIOS: dict[str, str] = {
    "campus": "10 anchors over 600 x 450 m, vehicle route over every road, 10 Hz poses, 20 Hz ranges (paper 001)",
    "small": "3 anchors over 60 x 45 m, the campus layout scaled by 0.1 (fast, for tests)",
}

_ROADS_X = np.array([0.0, 150.0, 300.0, 450.0, 600.0])  # north-south roads at these x
_ROADS_Y = np.array([0.0, 150.0, 300.0, 450.0])  # east-west roads at these y


def _terrain(xy: np.ndarray, scale: float) -> np.ndarray:
    x, y = xy[..., 0] / scale, xy[..., 1] / scale
    return 2.0 * np.sin(2 * np.pi * x / 600.0) + 1.5 * np.cos(2 * np.pi * y / 450.0)


def campus_layout(scale: float = 1.0):
    """Road grid, building blocks and route waypoints of the campus (host-side NumPy).

    Returns:
        (waypoints (W, 2) [m], buildings (B, 4) as xmin, ymin, xmax, ymax [m]).
    """
    rx, ry = _ROADS_X * scale, _ROADS_Y * scale
    inset = 15.0 * scale
    blocks = [
        (x0 + inset, y0 + inset, x1 - inset, y1 - inset)
        for x0, x1 in zip(rx[:-1], rx[1:], strict=True)
        for y0, y1 in zip(ry[:-1], ry[1:], strict=True)
    ]
    # Boustrophedon over the east-west roads, then over the north-south roads.
    wp = []
    for k, y in enumerate(ry):
        xs = (rx[0], rx[-1]) if k % 2 == 0 else (rx[-1], rx[0])
        wp += [(xs[0], y), (xs[1], y)]
    x_end = wp[-1][0]
    cols = rx if x_end == rx[0] else rx[::-1]
    for k, x in enumerate(cols):
        ys = (ry[-1], ry[0]) if k % 2 == 0 else (ry[0], ry[-1])
        wp += [(x, ys[0]), (x, ys[1])]
    return np.array(wp), np.array(blocks)


def _sample_path(wp: np.ndarray, speed: float, dt: float) -> np.ndarray:
    seg = np.diff(wp, axis=0)
    length = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(length)])
    s = np.arange(0.0, cum[-1], speed * dt)
    x = np.interp(s, cum, wp[:, 0])
    y = np.interp(s, cum, wp[:, 1])
    return np.stack([x, y], axis=1)


def _smooth(x: np.ndarray, width: int) -> np.ndarray:
    """Moving average along axis 0 with edge padding (rounds the corners of the route)."""
    k = np.ones(width) / width
    pad = np.pad(x, ((width // 2, width - 1 - width // 2), (0, 0)), mode="edge")
    return np.stack([np.convolve(pad[:, d], k, mode="valid") for d in range(x.shape[1])], axis=1)


def _crosses(p: np.ndarray, a: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(R,) True where the 2-D segment p -> a intersects any axis-aligned box (slab test)."""
    d = a - p  # (R, 2)
    hit = np.zeros(p.shape[0], dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        for b in boxes:
            t1 = (b[:2] - p) * inv
            t2 = (b[2:] - p) * inv
            tmin = np.nanmax(np.minimum(t1, t2), axis=1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=1)
            hit |= (tmax >= np.maximum(tmin, 0.0)) & (tmin <= 1.0)
    return hit


def simulate(
    scenario: str = "campus",
    seed: int = 0,
    drift: float = 0.0,
    channel: ChannelModel | None = None,
    max_range_m: float = 120.0,
    pose_rate_hz: float = 10.0,
    range_rate_hz: float = 20.0,
    speed_mps: float = 8.0,
    time_offset_s: float = 0.0,
) -> TrajectoryDataset:
    """Simulate a trajectory scenario (host-side NumPy; same seed, same dataset).

    Args:
        scenario: a key of `SCENARIOS`.
        seed: random seed (anchor placement, channel errors, drift).
        drift: odometry random-walk intensity [m / sqrt(s)], horizontal; 0 = exact poses.
        channel: ranging error model; `ChannelModel()` when None.
        max_range_m: no range beyond this distance (scaled with the scenario).
        pose_rate_hz, range_rate_hz: pose and per-anchor ranging rates [Hz].
        speed_mps: vehicle speed [m/s] (scaled with the scenario).
        time_offset_s: clock offset of the reported poses, pose clock minus range clock [s]: the pose taken
            at true time t is stamped t + time_offset_s (the ranges keep the true time); 0 = one clock.

    Returns:
        TrajectoryDataset with anchor truth, per-range LOS labels and one tag.
    """
    if scenario not in SCENARIOS:
        raise InputError(f"unknown trajectory scenario {scenario!r} (known: {', '.join(SCENARIOS)})")
    if drift < 0:
        raise InputError(f"drift must be >= 0, got {drift}")
    scale, n_anchors = (1.0, 10) if scenario == "campus" else (0.1, 3)
    gen = np.random.default_rng(seed)
    wp, blocks = campus_layout(scale)
    dt = 1.0 / pose_rate_hz
    speed = speed_mps * max(scale, 0.25)
    xy = _smooth(_sample_path(wp, speed, dt), max(1, int(round(2.0 / dt))))
    t = np.arange(xy.shape[0]) * dt
    z = _terrain(xy, scale)
    pos_true = np.column_stack([xy, z])
    heading = np.unwrap(np.arctan2(*np.gradient(xy, axis=0)[:, ::-1].T))
    quat = np.column_stack([np.zeros_like(heading), np.zeros_like(heading), np.sin(heading / 2), np.cos(heading / 2)])
    lever = np.array([[0.5, 0.0, 1.8]]) * (1.0 if scale == 1.0 else 0.5)

    # Anchors: beside roads at distinct places along the route, offset 4-8 m sideways, 3-6 m high.
    idx = np.sort(gen.choice(np.arange(xy.shape[0] // 20, xy.shape[0]), n_anchors, replace=False))
    side = gen.choice([-1.0, 1.0], n_anchors) * gen.uniform(4.0, 8.0, n_anchors) * max(scale, 0.25)
    normal = np.column_stack([-np.sin(heading[idx]), np.cos(heading[idx])])
    a_xy = xy[idx] + side[:, None] * normal
    anchors = np.column_stack([a_xy, _terrain(a_xy, scale) + gen.uniform(3.0, 6.0, n_anchors) * max(scale, 0.5)])

    # Ranging: every anchor at range_rate_hz, tag position from the true pose.
    rt = np.arange(0.0, t[-1], 1.0 / range_rate_hz) + 0.5 / range_rate_hz * gen.random()
    rt = rt[rt <= t[-1]]
    p_rt = np.column_stack([np.interp(rt, t, pos_true[:, d]) for d in range(3)])
    h_rt = np.interp(rt, t, heading)
    c, s = np.cos(h_rt), np.sin(h_rt)
    lv = lever[0]
    tag = p_rt + np.column_stack([c * lv[0] - s * lv[1], s * lv[0] + c * lv[1], np.full_like(c, lv[2])])
    r_idx = np.repeat(np.arange(rt.size), n_anchors)
    a_idx = np.tile(np.arange(n_anchors), rt.size)
    dist = np.linalg.norm(tag[r_idx] - anchors[a_idx], axis=1)
    keep = dist <= max_range_m * scale
    r_idx, a_idx, dist = r_idx[keep], a_idx[keep], dist[keep]
    los = ~_crosses(tag[r_idx, :2], anchors[a_idx, :2], blocks)
    err = sample_range_errors(gen, los, channel)
    rng_m = np.maximum(dist + err, 0.0)
    # Ranges within one round share a time stamp plus a small per-anchor slot offset.
    r_time = rt[r_idx] + a_idx * (0.4 / (range_rate_hz * n_anchors))

    pos_rep = pos_true.copy()
    if drift > 0:
        steps = gen.normal(0.0, drift * np.sqrt(dt), (t.size, 2))
        steps[0] = 0.0
        pos_rep[:, :2] += np.cumsum(steps, axis=0)
    order = np.argsort(r_time, kind="stable")
    return TrajectoryDataset(
        name=f"sim-{scenario}" + (f"-drift{drift:g}" if drift > 0 else ""),
        anchor_ids=tuple(f"A{i + 1:02d}" for i in range(n_anchors)),
        tag_ids=("T1",),
        lever_arm=lever,
        pose_time=t + time_offset_s,
        pose_position=pos_rep,
        pose_orientation=quat,
        range_time=r_time[order],
        range_anchor=a_idx[order],
        range_tag=np.zeros(order.size, np.int32),
        range=rng_m[order],
        range_los=los[order].astype(np.int8),
        anchor_truth=anchors,
        description=f"simulated {scenario}: {SCENARIOS[scenario]}; seed {seed}, drift {drift} m/sqrt(s)"
        + (f", pose clock offset {time_offset_s:g} s" if time_offset_s else ""),
        source="jaxcal.sim.trajectory",
    )
