"""Families of random meshes whose measured graph stresses the frame (issue #18, #24 item 1).

Each family is a random planar layout (`sim.mesh` with random positions, one interior wall, ~4 % of the
pairs never measured) with one structural defect, frame (0, 1, 2):

- `a0a1`, `a0a2`, `a1a2`: that frame pair is never measured (the network stays rigid: every node can be
  placed, through other nodes);
- `late`: the last node ranges only from the middle of the run on (placeable; available from then);
- `bridge`: two clusters (nodes 0..m-1 with the frame, and m+1..N-1) that range only through node m: the
  second cluster can rotate about m, so it cannot be placed;
- `leaf`: the last node ranges only one other node (not placeable: mirror/circle ambiguity).

`family_mesh(kind, seed)` is deterministic per seed.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxcal.data import MeshDataset
from jaxcal.errors import JaxcalError
from jaxcal.sim.mesh import MeshScenario, simulate

__all__ = ["FAMILIES", "family_mesh"]

FAMILIES = ("a0a1", "a0a2", "a1a2", "late", "bridge", "leaf")


def family_mesh(
    kind: str, seed: int, n_nodes: int = 12, n_epochs: int = 400, hall=(30.0, 20.0), never_share: float = 0.04
) -> MeshDataset:
    """A random mesh of family `kind` (module docstring).

    Args:
        kind: one of `FAMILIES`. seed: random seed.
        n_nodes: N (>= 8). n_epochs: epochs at 10 Hz. hall: (width, depth) [m].
        never_share: share of the other pairs never measured (at random, not touching the frame).

    Returns:
        A `MeshDataset` with truth and the configuration `default` = (0, 1, 2).
    """
    if kind not in FAMILIES:
        raise JaxcalError(f"unknown family {kind!r} (known: {', '.join(FAMILIES)})")
    if n_nodes < 8:
        raise JaxcalError(f"family meshes need at least 8 nodes, got {n_nodes}")
    rng = np.random.default_rng([seed, FAMILIES.index(kind)])
    n = n_nodes
    never: set[tuple[int, int]] = set()
    frame_pairs = {(0, 1), (0, 2), (1, 2)}
    others = [(i, j) for i in range(n) for j in range(i + 1, n) if (i, j) not in frame_pairs]
    k_never = int(round(never_share * len(others)))
    for idx in rng.choice(len(others), size=k_never, replace=False):
        never.add(others[int(idx)])
    if kind in ("a0a1", "a0a2", "a1a2"):
        never.add({"a0a1": (0, 1), "a0a2": (0, 2), "a1a2": (1, 2)}[kind])
    elif kind == "bridge":
        m = n // 2
        never |= {(i, j) for i in range(m) for j in range(m + 1, n)}
    elif kind == "leaf":
        keep = int(rng.integers(3, n - 1))
        never |= {(min(i, n - 1), max(i, n - 1)) for i in range(n - 1) if i != keep}
        never.discard((keep, n - 1))
    w, h = hall
    sc = MeshScenario(
        name=f"family-{kind}-{seed}",
        hall=(w, h),
        node_ids=tuple(f"n{i}" for i in range(n)),
        walls=(((0.5 * w, 0.0), (0.5 * w, 0.45 * h)),),
        n_epochs=n_epochs,
        never=tuple(sorted(never)),
        configs=(("default", (0, 1, 2)),),
        min_separation=2.0,
    )
    ds = simulate(sc, seed=seed)
    if kind == "late":
        r = np.array(ds.range)
        r[: n_epochs // 2, n - 1, :] = np.nan
        r[: n_epochs // 2, :, n - 1] = np.nan
        ds = dataclasses.replace(ds, range=r)
    return ds
