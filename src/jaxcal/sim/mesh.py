"""Mesh scenarios: nodes in a hall ranging each other, LOS/NLOS from wall segments.

`simulate("torgau", seed=0)` gives a `MeshDataset` shaped after the grid paper's Torgau campaign
(Section IV): 12 nodes at 1.60 m in a 44 x 30 m hall, interior walls that block about a quarter of the
links, 2,000 epochs at 10 Hz, ranging errors from `jaxcal.sim.channel` per LOS/NLOS class, random
per-measurement dropout (more for NLOS links) and a few pairs that are never measured. Two frame
configurations: `conf1` (three central, well-connected nodes) and `conf2` (awkward: a triangle in a
corner whose a1, "4503", never ranges to node "D5B4", after the paper's D5B4 case in Fig. 10).
Node ids are named after the paper's sensors where the paper names them; positions are invented.

Everything is deterministic per seed (NumPy `default_rng(seed)` spawned into independent streams).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from jaxcal.data import MeshDataset, mesh_true_distances
from jaxcal.errors import JaxcalError
from jaxcal.sim.channel import ChannelModel, sample_range_errors

__all__ = ["MeshScenario", "SCENARIOS", "simulate", "line_of_sight"]


@dataclass(frozen=True)
class MeshScenario:
    """Everything a mesh simulation needs (lengths in metres, times in seconds).

    Attributes:
        name: scenario name (also the dataset's name).
        hall: (width, depth) of the hall; random node positions are drawn inside it.
        node_ids: ids of the nodes; their number is the number of nodes.
        positions: (N, 2) node positions, or None to draw them uniformly in the hall (per seed) with
            at least `min_separation` between nodes.
        height: antenna height of every node (truth is 3-D with this z; ranges are then 2-D distances).
        walls: wall segments ((x0, y0), (x1, y1)); a link crossing any of them is NLOS.
        n_epochs, rate_hz: number of epochs and epoch rate.
        los_dropout, nlos_dropout: probability that one measurement is missing, per class.
        never: pairs (i, j) that are never measured (both directions).
        symmetric: one measurement per pair and epoch stored in both directions (as in the paper's
            matrices); otherwise i->j and j->i are measured independently.
        configs: name -> (a0, a1, a2).
        channel: ranging error model.
        bad_pairs: pairs (i, j) whose NLOS gross-outlier probability is `bad_pair_outlier_prob`
            instead of the channel's (real NLOS outliers cluster on a few links: Fig. 11b shows single
            pairs with RMSE over 17 m while most NLOS pairs stay near a metre).
        bad_pair_outlier_prob: gross-outlier probability on those pairs.
        min_separation: for random positions.
    """

    name: str
    hall: tuple[float, float]
    node_ids: tuple[str, ...]
    positions: tuple[tuple[float, float], ...] | None = None
    height: float = 1.6
    walls: tuple[tuple[tuple[float, float], tuple[float, float]], ...] = ()
    n_epochs: int = 2000
    rate_hz: float = 10.0
    los_dropout: float = 0.005
    nlos_dropout: float = 0.05
    never: tuple[tuple[int, int], ...] = ()
    symmetric: bool = True
    configs: tuple[tuple[str, tuple[int, int, int]], ...] = ()
    channel: ChannelModel = field(default_factory=ChannelModel)
    bad_pairs: tuple[tuple[int, int], ...] = ()
    bad_pair_outlier_prob: float = 0.5
    min_separation: float = 2.0


_TORGAU_IDS = (
    "4503",
    "8B05",
    "4197",
    "9911",
    "D5B4",
    "8AA5",
    "1C2F",
    "6E31",
    "A07B",
    "B3D9",
    "2F44",
    "C812",
)

SCENARIOS: dict[str, MeshScenario] = {
    "torgau": MeshScenario(
        name="torgau",
        hall=(44.0, 30.0),
        node_ids=_TORGAU_IDS,
        positions=(
            (3.0, 3.0),
            (22.0, 2.0),
            (41.0, 4.0),
            (41.0, 24.0),
            (30.0, 26.0),
            (6.0, 27.0),
            (15.0, 15.0),
            (29.0, 14.0),
            (12.0, 6.5),
            (37.0, 16.0),
            (20.0, 24.0),
            (4.0, 16.0),
        ),
        # an office room in the upper right corner (door gap at x = 25..27) and a shelf row
        walls=(
            ((27.0, 21.0), (35.0, 21.0)),
            ((35.0, 21.0), (35.0, 30.0)),
            ((9.0, 10.5), (14.0, 10.5)),
        ),
        never=((0, 4), (5, 3)),  # "4503"-"D5B4" as in the paper; "8AA5"-"9911" across the hall
        # three NLOS pairs carry most gross outliers (D5B4-8B05, D5B4-9911 as in the paper, 8AA5-A07B);
        # the other NLOS pairs get few, so that the class statistics keep Table I's shape
        bad_pairs=((4, 1), (4, 3), (5, 8)),
        bad_pair_outlier_prob=0.5,
        channel=ChannelModel(nlos_outlier_prob=0.025),
        configs=(("conf1", (6, 7, 10)), ("conf2", (1, 0, 11))),
    ),
    "small": MeshScenario(
        name="small",
        hall=(20.0, 15.0),
        node_ids=("N0", "N1", "N2", "N3", "N4", "N5"),
        walls=(((10.0, 0.0), (10.0, 11.0)),),
        n_epochs=200,
        configs=(("conf1", (0, 1, 2)),),
    ),
}


def _orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Sign of the 2-D cross product (b - a) x (c - a), broadcast over leading axes."""
    return np.sign(
        (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])
    )


def line_of_sight(positions: np.ndarray, walls) -> np.ndarray:
    """(N, N) bool: True where the segment between two nodes crosses no wall (proper intersection test).

    Args:
        positions: (N, 2) or (N, 3) node positions [m] (only x, y are used).
        walls: sequence of segments ((x0, y0), (x1, y1)).

    Returns:
        Symmetric bool matrix, True on the diagonal. Touching a wall's end point does not block.
    """
    p = np.asarray(positions, dtype=np.float64)[:, :2]
    n = p.shape[0]
    los = np.ones((n, n), dtype=bool)
    a, b = p[:, None, :], p[None, :, :]
    for w0, w1 in walls:
        c, d = np.asarray(w0, dtype=np.float64), np.asarray(w1, dtype=np.float64)
        o1, o2 = _orient(a, b, c), _orient(a, b, d)
        o3, o4 = _orient(c, d, a), _orient(c, d, b)
        los &= ~((o1 * o2 < 0) & (o3 * o4 < 0))
    return los


def _random_positions(rng: np.random.Generator, n: int, hall, min_sep: float) -> np.ndarray:
    w, h = hall
    pts: list[np.ndarray] = []
    for _ in range(100_000):
        q = rng.uniform((0.05 * w, 0.05 * h), (0.95 * w, 0.95 * h))
        if all(np.hypot(*(q - r)) >= min_sep for r in pts):
            pts.append(q)
            if len(pts) == n:
                return np.array(pts)
    raise JaxcalError(f"cannot place {n} nodes {min_sep} m apart in a {w} x {h} m hall")


def simulate(scenario: str | MeshScenario = "torgau", seed: int = 0, **overrides) -> MeshDataset:
    """Simulate a mesh ranging dataset.

    Args:
        scenario: a name in `SCENARIOS` or a `MeshScenario`.
        seed: random seed; the same seed (and scenario) gives identical arrays.
        **overrides: `MeshScenario` fields to replace (e.g. `n_epochs=100`, `rate_hz=2.0`).

    Returns:
        `MeshDataset` with `range` (K, N, N) [m], `truth` (N, 3) [m] (equal heights), `los` (N, N)
        int8, epoch times `k / rate_hz`, and the scenario's configurations.
    """
    if isinstance(scenario, str):
        if scenario not in SCENARIOS:
            raise JaxcalError(f"unknown mesh scenario {scenario!r} (known: {', '.join(sorted(SCENARIOS))})")
        sc = SCENARIOS[scenario]
    else:
        sc = scenario
    if overrides:
        known = {f.name for f in dataclasses.fields(MeshScenario)}
        bad = sorted(set(overrides) - known)
        if bad:
            raise JaxcalError(f"unknown scenario field(s) {', '.join(bad)} (known: {', '.join(sorted(known))})")
        sc = dataclasses.replace(sc, **overrides)
    n = len(sc.node_ids)
    if sc.n_epochs < 1 or sc.rate_hz <= 0:
        raise JaxcalError(f"need n_epochs >= 1 and rate_hz > 0, got {sc.n_epochs} and {sc.rate_hz}")

    rng_pos, rng_drop, rng_err = np.random.default_rng(seed).spawn(3)
    if sc.positions is not None:
        xy = np.asarray(sc.positions, dtype=np.float64)
        if xy.shape != (n, 2):
            raise JaxcalError(f"scenario {sc.name}: positions must be ({n}, 2), got {xy.shape}")
    else:
        xy = _random_positions(rng_pos, n, sc.hall, sc.min_separation)
    truth = np.column_stack([xy, np.full(n, sc.height)])
    dist = mesh_true_distances(truth)
    los = line_of_sight(xy, sc.walls)

    k = sc.n_epochs
    shape = (k, n, n)
    los_k = np.broadcast_to(los, shape)
    err = sample_range_errors(rng_err, los_k, sc.channel)
    if sc.bad_pairs:
        bad_pair = np.zeros((n, n), dtype=bool)
        for i, j in sc.bad_pairs:
            bad_pair[i, j] = bad_pair[j, i] = True
        worse = dataclasses.replace(sc.channel, nlos_outlier_prob=sc.bad_pair_outlier_prob)
        err = np.where(bad_pair & ~los, sample_range_errors(rng_err, los_k, worse), err)
    keep = rng_drop.random(shape) >= np.where(los, sc.los_dropout, sc.nlos_dropout)
    rng_ = np.maximum(dist[None] + err, 0.0)
    if sc.symmetric:
        upper = np.triu(np.ones((n, n), dtype=bool), 1)
        rng_ = np.where(upper, rng_, np.swapaxes(rng_, 1, 2))
        keep = np.where(upper, keep, np.swapaxes(keep, 1, 2))
    for i, j in sc.never:
        keep[:, i, j] = keep[:, j, i] = False
    keep[:, np.arange(n), np.arange(n)] = False
    ranges = np.where(keep, rng_, np.nan).astype(np.float32)

    los_i8 = los.astype(np.int8)
    return MeshDataset(
        name=sc.name,
        node_ids=sc.node_ids,
        time=np.arange(k, dtype=np.float64) / sc.rate_hz,
        range=ranges,
        truth=truth,
        los=los_i8,
        configs=tuple(sc.configs),
        description=f"simulated mesh scenario {sc.name!r}, seed {seed} (jaxcal.sim.mesh)",
        source="jaxcal simulator",
        license="CC0-1.0",
    )
