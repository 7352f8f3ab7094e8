"""Large random mesh networks at constant density: the node count grows, the site grows with it.

Warehouses, tunnels and stadiums run 50-300 UWB nodes, each ranging only the neighbours within radio
range. `network_scenario(n_nodes, seed=...)` lays out such a site for `sim.mesh.simulate`:

- the hall's area is `n_nodes / density` (density in nodes per 100 m^2; default 1/60 m^2, so 10 nodes
  fill the 30 x 20 m hall of the other random families), aspect 3:2;
- node positions uniform in the hall, at least `min_separation` apart; nodes 0, 1, 2 are the three
  nodes nearest the hall's centre (the frame configuration `conf1`), the others in random order;
- walls: `wall_density` axis-aligned segments per 100 m^2 (default 2 per 600 m^2), each 4-12 m long,
  uniform in the hall; a link crossing one is NLOS (`sim.mesh.line_of_sight`);
- pairs farther apart than `range_limit_m` are never measured (radio range).

Deterministic per seed. `jaxcal simulate mesh --scenario network --nodes N ...` writes one.
"""

from __future__ import annotations

import math

import numpy as np

from jaxcal.errors import JaxcalError
from jaxcal.sim.mesh import MeshScenario, _random_positions

__all__ = ["network_scenario"]


def network_scenario(
    n_nodes: int,
    seed: int = 0,
    density: float = 100.0 / 60.0,
    range_limit_m: float = 28.0,
    wall_density: float = 2.0 / 6.0,
    n_epochs: int = 200,
    min_separation: float = 2.0,
) -> MeshScenario:
    """A random network of `n_nodes` at constant density (module docstring).

    Args:
        n_nodes: N (>= 4). seed: random seed (layout and walls; ranges use `simulate`'s seed).
        density: nodes per 100 m^2. range_limit_m: longest measured pair [m].
        wall_density: walls per 100 m^2. n_epochs: epochs at 10 Hz.
        min_separation: least distance between nodes [m].
    """
    if n_nodes < 4:
        raise JaxcalError(f"a network needs at least 4 nodes, got {n_nodes}")
    for name, value in (("density", density), ("range_limit_m", range_limit_m)):
        if not (value > 0 and math.isfinite(value)):
            raise JaxcalError(f"{name} must be a positive number, got {value}")
    if not (wall_density >= 0 and math.isfinite(wall_density)):
        raise JaxcalError(f"wall_density must be >= 0, got {wall_density}")
    if n_epochs < 1:
        raise JaxcalError(f"n_epochs must be >= 1, got {n_epochs}")
    area = 100.0 * n_nodes / density
    width = math.sqrt(1.5 * area)
    depth = area / width
    rng_pos, rng_wall = np.random.default_rng([seed, 2026]).spawn(2)
    xy = _random_positions(rng_pos, n_nodes, (width, depth), min_separation)
    centre = np.array([width / 2, depth / 2])
    near = np.argsort(np.hypot(*(xy - centre).T), kind="stable")
    order = np.concatenate([near[:3], rng_pos.permutation(near[3:])])
    xy = xy[order]
    walls = []
    for _ in range(int(round(wall_density * area / 100.0))):
        length = rng_wall.uniform(4.0, 12.0)
        x0, y0 = rng_wall.uniform((0.0, 0.0), (width, depth))
        if rng_wall.random() < 0.5:
            walls.append(((x0, y0), (min(x0 + length, width), y0)))
        else:
            walls.append(((x0, y0), (x0, min(y0 + length, depth))))
    d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1))
    far = np.argwhere(np.triu(d > range_limit_m, 1))
    width_digits = len(str(n_nodes - 1))
    return MeshScenario(
        name=f"network{n_nodes}",
        hall=(width, depth),
        node_ids=tuple(f"n{i:0{width_digits}d}" for i in range(n_nodes)),
        positions=tuple(map(tuple, xy)),
        walls=tuple(walls),
        n_epochs=n_epochs,
        never=tuple((int(i), int(j)) for i, j in far.tolist()),
        configs=(("conf1", (0, 1, 2)),),
        min_separation=min_separation,
    )
