"""Which nodes the measured ranges fix in the frame of (a0, a1, a2): one decision for every mesh method.

A node is *fixed* (placeable) when the graph of measured pairs determines its coordinates in the frame
of CONTRACT 1.1 (a0 at the origin, a1 on +x, a2 at y > 0), for generic positions:

1. **Connected**: it lies in a0's connected component of the measured graph (scipy.sparse.csgraph).
2. **Rigid in the frame** (infinitesimal, generic rigidity): the rigidity matrix of the measured pairs
   at a random configuration, stacked with the gauge rows of the frame (a0's coordinates; a1's y (and
   z); in 3-D a2's z), has a null space (the flexes left once the frame is fixed); the node is rigid
   when it does not move in any of them. At a random configuration this rank test is exact with
   probability 1 (Gluck 1975; Asimow & Roth 1978), whatever the true layout.
3. **No mirror image**: a rigid node with only d fixed neighbours (d = 2 in 2-D) can be reflected
   through the line (plane) of its neighbours without changing one range, so it is not fixed. The
   frame nodes first follow their own rule: a1 needs a range to a0 or two fixed neighbours, a2 a
   range to both a0 and a1 or three fixed neighbours. Such nodes are peeled off and the test repeats
   on what is left (a node that relied on a peeled one may lose its rigidity); this is the generic
   necessary condition for global rigidity (Hendrickson 1992), conservative where the exact test
   (3-connectivity plus redundant rigidity, Jackson & Jordan 2005) would keep a node.
4. **Frame determined**: a1 and a2 are fixed themselves, and, when any other node is fixed, each of
   a0, a1, a2 has more than d fixed neighbours. A frame node with only d (a2 ranging a0 and a1
   only, a1 ranging a0 and one more) has a mirror image: reflecting it through its neighbours'
   line keeps every range, and the frame it spans flips against the rest, so every other node has
   two placements in the frame ("frame has a mirror image"). Otherwise only a0, a1 (its range to
   a0) and a2 (its ranges to both) can be placed.

`identify` is pure NumPy/SciPy on an (N, N) graph (no ranges needed beyond which pairs were measured).
Which triple to use as the frame is `frame_choice.py`'s job; turning the answer into NaN rows of a
`Result` and one warning line is `masking.py`'s.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

FRAME_UNDETERMINED = "frame not determined"

__all__ = [
    "Identifiability",
    "measured_pairs",
    "identify",
    "identify_ranges",
    "FRAME_UNDETERMINED",
]


@dataclass(frozen=True)
class Identifiability:
    """Per-node answer of `identify`.

    Attributes:
        anchors: (a0, a1, a2). dim: 2 or 3.
        fixed: (N,) bool, the node's position in the frame is determined by the measured pairs.
        reason: (N,) why a node is not fixed ("" when fixed).
        frame_fixed: a1 and a2 are fixed (the frame is determined).
        missing_frame_links: frame pairs (i, j), i < j, never measured.
        never_ranged: every pair (i, j), i < j, never measured.
        mirror: why the frame has a mirror image ("n2 ranges only n0, n1"; "" when it has none).
    """

    anchors: tuple[int, int, int]
    dim: int
    fixed: np.ndarray
    reason: tuple[str, ...]
    frame_fixed: bool
    missing_frame_links: tuple[tuple[int, int], ...]
    never_ranged: tuple[tuple[int, int], ...]
    mirror: str = ""

    @property
    def n_fixed(self) -> int:
        return int(self.fixed.sum())


def measured_pairs(range_m: np.ndarray, min_count: int = 1) -> np.ndarray:
    """(N, N) symmetric bool: pair i-j measured (either direction) in at least `min_count` epochs.

    Args:
        range_m: (K, N, N) ranges [m], NaN = not measured.
        min_count: least number of epochs with a range.
    """
    r = np.asarray(range_m)
    cnt = np.isfinite(r).sum(axis=0)
    cnt = cnt + cnt.T
    a = cnt >= max(int(min_count), 1)
    np.fill_diagonal(a, False)
    return a


def _gauge_rows(anchors, dim: int, cols: dict[int, int]) -> list[np.ndarray]:
    a0, a1, a2 = anchors
    fixed = [(a0, c) for c in range(dim)] + [(a1, c) for c in range(1, dim)]
    if dim == 3:
        fixed.append((a2, 2))
    rows = []
    for node, c in fixed:
        if node in cols:
            row = np.zeros(len(cols) * dim)
            row[cols[node] * dim + c] = 1.0
            rows.append(row)
    return rows


def _rigid_in_frame(adj: np.ndarray, nodes: np.ndarray, anchors, dim: int, x: np.ndarray) -> np.ndarray:
    """(len(nodes),) bool: node does not move in any flex of the framework (`nodes`, `adj`) with the
    frame's gauge fixed, at configuration `x` (N, dim)."""
    cols = {int(v): k for k, v in enumerate(nodes)}
    m = len(nodes)
    sub = adj[np.ix_(nodes, nodes)]
    ii, jj = np.nonzero(np.triu(sub, 1))
    rows = np.zeros((ii.size, m * dim))
    diff = x[nodes[ii]] - x[nodes[jj]]
    for c in range(dim):
        rows[np.arange(ii.size), ii * dim + c] = diff[:, c]
        rows[np.arange(ii.size), jj * dim + c] = -diff[:, c]
    g = _gauge_rows(anchors, dim, cols)
    mat = np.vstack([rows] + ([np.stack(g)] if g else []))
    if mat.shape[0] == 0:
        return np.zeros(m, dtype=bool)
    _, s, vt = np.linalg.svd(mat, full_matrices=mat.shape[0] < mat.shape[1])
    tol = max(mat.shape) * np.finfo(float).eps * 1e4 * (s[0] if s.size else 1.0)
    rank = int((s > tol).sum())
    null = vt[rank:]  # (flexes, m * dim)
    if null.shape[0] == 0:
        return np.ones(m, dtype=bool)
    motion = np.linalg.norm(null.T.reshape(m, dim, -1), axis=(1, 2))
    return motion < 1e-6


def _mirror_ok(i: int, nb: set[int], anchors, dim: int) -> bool:
    a0, a1, a2 = anchors
    if i == a0:
        return True
    if i == a1:
        return a0 in nb or len(nb) >= 2
    if i == a2:
        return {a0, a1} <= nb or len(nb) >= 3
    return len(nb) >= dim + 1


def _names(idx, ids) -> str:
    return ", ".join(str(ids[int(k)]) for k in idx)


def identify(measured: np.ndarray, anchors, dim: int = 2, ids=None, seed: int = 0) -> Identifiability:
    """Decide per node whether the measured graph fixes it in the frame of `anchors` (module docstring).

    Args:
        measured: (N, N) bool, pair measured (symmetric; see `measured_pairs`).
        anchors: (a0, a1, a2) node indices.
        dim: 2 or 3.
        ids: node ids for the reasons (default: indices).
        seed: seed of the random configuration (the answer is the same for almost every seed).

    Returns:
        An `Identifiability`.
    """
    adj = np.asarray(measured, dtype=bool)
    adj = adj | adj.T
    n = adj.shape[0]
    np.fill_diagonal(adj, False)
    ids = [str(k) for k in range(n)] if ids is None else [str(v) for v in ids]
    a0, a1, a2 = (int(a) for a in anchors)
    anchors = (a0, a1, a2)
    reason = [""] * n
    _, label = connected_components(csr_matrix(adj), directed=False)
    alive = label == label[a0]
    deg = adj.sum(axis=1)
    for i in range(n):
        if deg[i] == 0:
            reason[i] = f"{ids[i]} never ranged"
        elif not alive[i]:
            reason[i] = f"{ids[i]} is not connected to a0 {ids[a0]}"
    x = np.random.default_rng(seed).uniform(0.0, 1.0, (n, dim))
    fixed = np.zeros(n, dtype=bool)
    while True:
        nodes = np.flatnonzero(alive)
        fixed = np.zeros(n, dtype=bool)
        fixed[nodes] = _rigid_in_frame(adj, nodes, anchors, dim, x)
        peel = []
        for k in np.flatnonzero(fixed).tolist():
            placed = set(np.flatnonzero(adj[k] & fixed).tolist())
            if not _mirror_ok(k, placed, anchors, dim):
                peel.append(k)
                only = sorted(placed)
                reason[k] = f"{ids[k]} ranges only {_names(only, ids)}" if only else f"{ids[k]} has no fixed neighbour"
        if not peel:
            break
        alive[peel] = False
    frame_fixed = bool(fixed[a1] and fixed[a2])
    mirror = _frame_mirror(adj, fixed, anchors, dim, ids) if frame_fixed else ""
    frame_fixed = frame_fixed and not mirror
    for i in range(n):
        if not fixed[i] and not reason[i]:
            nbrs = np.flatnonzero(adj[i])
            if nbrs.size <= dim:
                reason[i] = f"{ids[i]} ranges only {_names(nbrs, ids)}"
            else:
                reason[i] = f"{ids[i]} is not rigidly connected to the frame (ranges {_names(nbrs, ids)})"
    if not frame_fixed:
        keep = {a0} | ({a1} if fixed[a1] else set())
        if mirror:  # the frame triangle keeps its shape in any reflection: its measured sides fix it
            keep = {a0} | ({a1} if adj[a0, a1] else set())
            keep |= {a2} if adj[a0, a1] and adj[a0, a2] and adj[a1, a2] else set()
        for i in range(n):
            if i not in keep and i not in (a1, a2):
                reason[i] = FRAME_UNDETERMINED
        fixed = np.isin(np.arange(n), sorted(keep))
    pairs = [(i, j) for i, j in itertools.combinations(range(n), 2) if not adj[i, j]]
    missing = tuple((min(i, j), max(i, j)) for i, j in ((a0, a1), (a0, a2), (a1, a2)) if not adj[i, j])
    return Identifiability(
        anchors=anchors,
        dim=dim,
        fixed=fixed,
        reason=tuple("" if fixed[i] else reason[i] for i in range(n)),
        frame_fixed=frame_fixed,
        missing_frame_links=missing,
        never_ranged=tuple(pairs),
        mirror=mirror,
    )


def _frame_mirror(adj: np.ndarray, fixed: np.ndarray, anchors, dim: int, ids) -> str:
    """Why the frame has a mirror image: the first frame node with only `dim` fixed neighbours while a
    node outside the frame is fixed ("" when none; a lone frame triangle is rigid as it is)."""
    others = fixed.copy()
    others[list(anchors)] = False
    if not others.any():
        return ""
    for f in anchors:
        nb = np.flatnonzero(adj[f] & fixed)
        if nb.size <= dim:
            return f"{ids[f]} ranges only {_names(nb, ids)}"
    return ""


def identify_ranges(range_m: np.ndarray, anchors, dim: int = 2, ids=None, min_count: int = 1) -> Identifiability:
    """`identify` on the pairs measured in (K, N, N) ranges (at least `min_count` epochs)."""
    return identify(measured_pairs(range_m, min_count), anchors, dim, ids)
