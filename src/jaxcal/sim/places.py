"""A simulated repetitive environment for place recognition: a container yard with UWB anchors.

Container rows run along x, separated by aisles every `row_pitch_m`; cross aisles run along y every
`cross_pitch_m`. A prior mapping run drives every aisle and drops a keyframe every
`keyframe_step_m`; a later run (the queries) follows the same aisles with a lateral offset, as in
Table II of the second paper ("the testing sequence overlaps with the prior but with offset").

The descriptor of a place is a stand-in for any global place-recognition descriptor (STD, Scan
Context...): a sum of two random-Fourier-feature fields of the position,

    desc(p) = repeat * R(phi(p)) + unique * U(p) + noise,

where `phi(p)` maps p onto the container period (x modulo `container_pitch_m`, y modulo
`row_pitch_m`) so that `R` is identical at every repetition of the pattern, and `U` is a smooth
field of length scale `unique_scale_m` (the few distinctive things: a lamp post, a parked truck).
Map and
query descriptors get independent noise. With a large `repeat` / `unique` ratio, many places far
apart look alike and an ungated nearest-descriptor search often lands in the wrong aisle. The
default `unique = 0.3` was chosen so that the ungated search succeeds on roughly 40 % of the
queries (43 % on seed 0), the regime of the paper's STD baseline; it is a knob of
the scene, not of the gating.

Ranges from the platform to the anchors: true distance plus the LOS/NLOS error mixture of
`jaxcal.sim.channel` (NLOS with probability `nlos_share`), only within `max_range_m`.
Host-side NumPy: simulation happens once, outside traced code.
"""

from __future__ import annotations

import equinox as eqx
import numpy as np

from jaxcal.errors import InputError
from jaxcal.sim.channel import ChannelModel, sample_range_errors

__all__ = ["PlaceConfig", "PlaceScene", "simulate_places", "perturb_anchors"]


class PlaceConfig(eqx.Module):
    """Parameters of the simulated yard (metres unless stated).

    Attributes:
        width_m, height_m: yard extent along x and y.
        row_pitch_m: spacing of the aisles along x (container rows between them).
        cross_pitch_m: spacing of the cross aisles along y.
        container_pitch_m: repetition period of the scenery along an aisle.
        keyframe_step_m: spacing of prior keyframes along the route.
        descriptor_dim: F, length of a descriptor.
        repeat, unique: weights of the repeating and the place-unique descriptor fields.
        unique_scale_m: correlation length of the unique field.
        map_noise, query_noise: descriptor noise (per component, relative to unit-variance fields).
        query_offset_m: maximum lateral offset of the query run from the prior route.
        n_anchors_x, n_anchors_y: anchors on a jittered grid; anchor_height_m: their height.
        max_range_m: ranges beyond this are not heard.
        nlos_share: probability that a range is NLOS (channel model of `jaxcal.sim.channel`).
        speed_mps: platform speed, for the time stamps.
    """

    width_m: float = 600.0
    height_m: float = 450.0
    row_pitch_m: float = 16.0
    cross_pitch_m: float = 75.0
    container_pitch_m: float = 12.5
    keyframe_step_m: float = 1.5
    descriptor_dim: int = 256
    repeat: float = 1.0
    unique: float = 0.3
    unique_scale_m: float = 4.0
    map_noise: float = 0.15
    query_noise: float = 0.35
    query_offset_m: float = 1.5
    n_anchors_x: int = 4
    n_anchors_y: int = 3
    anchor_height_m: float = 6.0
    max_range_m: float = 250.0
    nlos_share: float = 0.2
    speed_mps: float = 3.0


class PlaceScene(eqx.Module):
    """One simulated yard: anchors, the prior keyframe map and a query run (NumPy arrays).

    Attributes:
        anchor_truth: (A, 3) true anchor positions [m].
        keyframe_time: (K,) [s]; keyframe_position: (K, 3) [m]; keyframe_descriptor: (K, F) float32.
        keyframe_range: (K, A) float32 ranges keyframe -> anchor [m], NaN = not heard.
        query_time: (Q,) [s]; query_position: (Q, 3) true query positions [m];
        query_descriptor: (Q, F) float32; query_range: (Q, A) float32 [m], NaN = not heard.
        query_los: (Q, A) bool, True where the query range was LOS.
    """

    anchor_truth: np.ndarray
    keyframe_time: np.ndarray
    keyframe_position: np.ndarray
    keyframe_descriptor: np.ndarray
    keyframe_range: np.ndarray
    query_time: np.ndarray
    query_position: np.ndarray
    query_descriptor: np.ndarray
    query_range: np.ndarray
    query_los: np.ndarray


def _route(cfg: PlaceConfig) -> tuple[np.ndarray, np.ndarray]:
    """Points along every aisle (N, 2) and the unit direction of travel at each (N, 2)."""
    pts, dirs = [], []
    step = cfg.keyframe_step_m
    ys = np.arange(cfg.row_pitch_m / 2, cfg.height_m, cfg.row_pitch_m)
    for i, y in enumerate(ys):  # lawn-mower through the aisles along x
        x = np.arange(0.0, cfg.width_m, step)
        x = x if i % 2 == 0 else x[::-1]
        pts.append(np.stack([x, np.full_like(x, y)], 1))
        dirs.append(np.tile([1.0 if i % 2 == 0 else -1.0, 0.0], (x.size, 1)))
    xs = np.arange(cfg.cross_pitch_m / 2, cfg.width_m, cfg.cross_pitch_m)
    for i, xc in enumerate(xs):  # then the cross aisles along y
        ya = np.arange(0.0, cfg.height_m, step)
        ya = ya if i % 2 == 0 else ya[::-1]
        pts.append(np.stack([np.full_like(ya, xc), ya], 1))
        dirs.append(np.tile([0.0, 1.0 if i % 2 == 0 else -1.0], (ya.size, 1)))
    return np.concatenate(pts), np.concatenate(dirs)


class _Field:
    """Random Fourier features, unit variance: <f(p), f(p')> ~ exp(-|p - p'|^2 / (2 l^2))."""

    def __init__(self, rng: np.random.Generator, in_dim: int, out_dim: int, scale: float):
        self.w = rng.normal(size=(in_dim, out_dim)) / scale
        self.b = rng.uniform(0, 2 * np.pi, out_dim)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return np.sqrt(2.0) * np.cos(x @ self.w + self.b)


def _periodic(p: np.ndarray, cfg: PlaceConfig) -> np.ndarray:
    """Embed positions on the repetition torus (x mod container pitch, y mod row pitch)."""
    ax = 2 * np.pi * p[:, 0] / cfg.container_pitch_m
    ay = 2 * np.pi * p[:, 1] / cfg.row_pitch_m
    # radius ~ period / (2 pi): distances on the torus are close to metres for small offsets
    rx, ry = cfg.container_pitch_m / (2 * np.pi), cfg.row_pitch_m / (2 * np.pi)
    return np.stack([rx * np.cos(ax), rx * np.sin(ax), ry * np.cos(ay), ry * np.sin(ay)], 1)


def _ranges(rng, cfg: PlaceConfig, pos: np.ndarray, anchors: np.ndarray, channel: ChannelModel):
    d = np.linalg.norm(pos[:, None, :] - anchors[None, :, :], axis=-1)
    los = rng.random(d.shape) >= cfg.nlos_share
    r = d + sample_range_errors(rng, los, channel)
    r = np.where(d <= cfg.max_range_m, np.maximum(r, 0.0), np.nan)
    return r.astype(np.float32), los


def simulate_places(
    seed: int,
    config: PlaceConfig | None = None,
    n_queries: int = 500,
    channel: ChannelModel | None = None,
    anchors: np.ndarray | None = None,
) -> PlaceScene:
    """Simulate a repetitive yard, its prior keyframe map and a query run.

    Args:
        seed: random seed (the environment, the noise and the queries all follow from it).
        config: yard parameters; `PlaceConfig()` when None.
        n_queries: Q, number of query places along the route.
        channel: ranging error model; `ChannelModel()` when None.
        anchors: (A, 3) true anchor positions [m] to use instead of the jittered grid (e.g. the
            anchors of another scenario over the same area); keyframes, queries and descriptors
            are the same as without it for the same seed.

    Returns:
        A `PlaceScene`.
    """
    cfg = PlaceConfig() if config is None else config
    channel = ChannelModel() if channel is None else channel
    if n_queries < 1:
        raise InputError(f"n_queries must be >= 1, got {n_queries}")
    rng = np.random.default_rng(seed)
    f = cfg.descriptor_dim
    rep_field = _Field(rng, 4, f, 1.0)
    uni_field = _Field(rng, 2, f, cfg.unique_scale_m)

    def describe(p2: np.ndarray, noise: float) -> np.ndarray:
        d = cfg.repeat * rep_field(_periodic(p2, cfg)) + cfg.unique * uni_field(p2)
        return (d + noise * rng.normal(size=d.shape)).astype(np.float32)

    route, dirs = _route(cfg)
    k = route.shape[0]
    kf_pos = np.column_stack([route, np.zeros(k)])
    kf_time = np.arange(k) * (cfg.keyframe_step_m / cfg.speed_mps)

    gx = (np.arange(cfg.n_anchors_x) + 0.5) * cfg.width_m / cfg.n_anchors_x
    gy = (np.arange(cfg.n_anchors_y) + 0.5) * cfg.height_m / cfg.n_anchors_y
    grid = np.array([(x, y) for y in gy for x in gx])
    jitter = rng.uniform(-0.2, 0.2, grid.shape) * np.array(
        [cfg.width_m / cfg.n_anchors_x, cfg.height_m / cfg.n_anchors_y]
    )
    grid_anchors = np.column_stack([grid + jitter, np.full(len(grid), cfg.anchor_height_m)])
    if anchors is None:
        anchors = grid_anchors
    else:
        anchors = np.asarray(anchors, dtype=np.float64)
        if anchors.ndim != 2 or anchors.shape[1] != 3 or not np.all(np.isfinite(anchors)):
            raise InputError(f"anchors: expected finite (A, 3) positions, got shape {anchors.shape}")

    # Query run: random places along the route, shifted along and across the aisle.
    pick = np.sort(rng.choice(k, size=n_queries, replace=n_queries > k))
    normal = np.stack([-dirs[pick, 1], dirs[pick, 0]], 1)
    along = rng.uniform(-0.5, 0.5, n_queries) * cfg.keyframe_step_m
    across = rng.uniform(-1.0, 1.0, n_queries) * cfg.query_offset_m
    q2 = route[pick] + along[:, None] * dirs[pick] + across[:, None] * normal
    q_pos = np.column_stack([q2, np.zeros(n_queries)])
    q_time = kf_time[-1] + 10.0 + np.arange(n_queries) * 1.0

    kf_desc = describe(route, cfg.map_noise)
    q_desc = describe(q2, cfg.query_noise)
    kf_range, _ = _ranges(rng, cfg, kf_pos, anchors, channel)
    q_range, q_los = _ranges(rng, cfg, q_pos, anchors, channel)
    return PlaceScene(
        anchor_truth=anchors,
        keyframe_time=kf_time,
        keyframe_position=kf_pos,
        keyframe_descriptor=kf_desc,
        keyframe_range=kf_range,
        query_time=q_time,
        query_position=q_pos,
        query_descriptor=q_desc,
        query_range=q_range,
        query_los=q_los,
    )


def perturb_anchors(rng: np.random.Generator, truth: np.ndarray, error_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Anchors 'calibrated' with a controlled error: truth + N(0, (error_m^2 / D) I) per anchor.

    Args:
        rng: random generator. truth: (A, D) true positions [m].
        error_m: root-mean-square 3-D (or D-D) position error [m].

    Returns:
        (position (A, D), covariance (A, D, D)) with the honest covariance (error_m^2 / D) I.
    """
    a, d = truth.shape
    var = error_m**2 / d
    pos = truth + np.sqrt(var) * rng.normal(size=truth.shape)
    return pos, np.tile(var * np.eye(d), (a, 1, 1))
