"""The problem `solve` works on: a validated range stream restricted to the nodes connected to a0, with its
per-pair median observations (`_prepare`), and the padding of observations to few distinct lengths."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from jaxcal.errors import JaxcalError
from jaxcal.mesh.batch.params import BatchParams, Observations, observations, spread_weights


def _bucket(m: int) -> int:
    """Padded length >= m from the sequence 16, 24, 32, 48, 64, ... (fewer distinct shapes to compile)."""
    size = 16
    while size < m:
        size = size * 3 // 2 if size & (size - 1) == 0 else size * 4 // 3
    return size


def _pad(a: np.ndarray, size: int) -> np.ndarray:
    """`a` padded with zeros to `size` (padded observations get weight 0 and contribute nothing)."""
    return np.concatenate([a, np.zeros(size - a.shape[0], dtype=a.dtype)])


def _active_nodes(i: np.ndarray, j: np.ndarray, n: int, a0: int) -> np.ndarray:
    """Boolean (N,) mask of the nodes connected to a0 through measured pairs."""
    adj: list[list[int]] = [[] for _ in range(n)]
    for u, v in zip(i.tolist(), j.tolist(), strict=False):
        adj[u].append(v)
        adj[v].append(u)
    seen = np.zeros(n, dtype=bool)
    stack = [a0]
    seen[a0] = True
    while stack:
        u = stack.pop()
        for v in adj[u]:
            if not seen[v]:
                seen[v] = True
                stack.append(v)
    return seen


def _pair_matrix(obs: Observations, m: int) -> np.ndarray:
    """(m, m) symmetric weights of the measured pairs (0 = not measured) of one-per-pair observations."""
    w = np.zeros((m, m))
    oi, oj, ow = np.asarray(obs.i), np.asarray(obs.j), np.asarray(obs.w)
    w[oi, oj] = w[oj, oi] = np.where(ow > 0, ow, w[oi, oj])
    return w


@dataclasses.dataclass(frozen=True)
class _Problem:
    """A validated range stream, restricted to the nodes connected to a0 (the `m` active nodes).

    Attributes:
        ranges: (K, N, N) ranges [m], NaN = missing.
        node_ids: (N,) ids (for messages).
        anchors: (a0, a1, a2) indices of the frame nodes among all N.
        active: (N,) bool, the nodes connected to a0 through measured pairs.
        sub: (m,) indices of the active nodes; remap: (N,) index among them (-1 if inactive).
        pair_weights: (N, N) weights of `pair_weight=spread`, or None.
        pairs: the per-pair median observations between active nodes (padded, `_bucket`).
        pair_i, pair_j: (M,) node indices (i < j) of the measured pairs (the real rows of `pairs`).
        distances: (m, m) the pairs' median ranges [m] (symmetric, NaN = not measured).
    """

    ranges: np.ndarray
    node_ids: tuple[str, ...]
    anchors: tuple[int, int, int]
    active: np.ndarray
    sub: np.ndarray
    remap: np.ndarray
    pair_weights: np.ndarray | None
    pairs: Observations
    pair_i: np.ndarray
    pair_j: np.ndarray
    distances: np.ndarray

    @property
    def n(self) -> int:
        return self.ranges.shape[1]

    @property
    def m(self) -> int:
        return self.sub.size

    def observations(self, i: np.ndarray, j: np.ndarray, z: np.ndarray, w: np.ndarray) -> Observations:
        """Observations between active nodes (indices among them), padded to a `_bucket` length."""
        return _active_observations(self.active, self.remap, i, j, z, w)


def _active_observations(
    active: np.ndarray, remap: np.ndarray, i: np.ndarray, j: np.ndarray, z: np.ndarray, w: np.ndarray
) -> Observations:
    """The observations (i, j, z, w) between active nodes, indices among them, padded to a `_bucket` length."""
    keep = active[i] & active[j]
    size = _bucket(int(keep.sum()))
    return Observations(
        *(
            jnp.asarray(_pad(a, size))
            for a in (remap[i[keep]], remap[j[keep]], z[keep].astype(float), w[keep].astype(float))
        )
    )


def _prepare(
    range_m: np.ndarray, anchors: tuple[int, int, int], p: BatchParams, node_ids: tuple[str, ...] | None
) -> _Problem:
    """Validate the range stream and the frame nodes; the per-pair median observations between active nodes."""
    r = np.asarray(range_m, dtype=np.float64)
    if r.ndim != 3 or r.shape[1] != r.shape[2]:
        raise JaxcalError(f"batch: expected ranges of shape (K, N, N), got {r.shape}")
    n = r.shape[1]
    ids = node_ids or tuple(str(k) for k in range(n))
    a0, a1, a2 = anchors
    i_m, j_m, z_m, w_m = observations(r, "median")
    pw = spread_weights(r) if p.pair_weight == "spread" else None
    if pw is not None:
        w_m = pw[i_m, j_m]
    if z_m.size == 0:
        raise JaxcalError("batch: the dataset has no finite ranges")
    active = _active_nodes(i_m, j_m, n, a0)
    for a in (a1, a2):
        if not active[a]:
            raise JaxcalError(f"batch: frame node {ids[a]!r} has no ranges connecting it to a0 {ids[a0]!r}")
    if active.sum() < p.dim + 1:
        raise JaxcalError(f"batch: need at least {p.dim + 1} connected nodes, got {int(active.sum())}")
    sub = np.flatnonzero(active)
    remap = -np.ones(n, dtype=np.int64)
    remap[sub] = np.arange(sub.size)
    m = len(sub)
    obs_med = _active_observations(active, remap, i_m, j_m, z_m, w_m)
    d_pair = np.full((m, m), np.nan)
    real = np.asarray(obs_med.w) > 0
    mi, mj, mz = np.asarray(obs_med.i)[real], np.asarray(obs_med.j)[real], np.asarray(obs_med.z)[real]
    d_pair[mi, mj] = mz
    d_pair[mj, mi] = mz
    return _Problem(r, ids, (a0, a1, a2), active, sub, remap, pw, obs_med, mi, mj, d_pair)
