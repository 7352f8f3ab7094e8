"""Which frame (a0, a1, a2) to place a recording in: the `--config auto` triple and a grid filter's frame.

`choose_frame` ranks the triples whose three pairs are measured by the nodes the ranges fix in their frame
(`identify.identify`), then by how often the three pairs are measured, the triangle's shape and the
nodes' degree. A grid filter (pgp, parametric) places a node only once it has ranged `min_refs` placed
nodes (`trilateration_reach`), so `filter_frame` picks the frame it should run in: the configuration's
own when the paper's frame rule applies early and reaches as many fixed nodes as any other, else the
best reachable triple (the caller moves the track back into the configuration's frame).
`with_auto_config` names `choose_frame`'s triple `auto`.

Pure NumPy on the measured graph and the median ranges; the rigidity test is `identify.py`'s.
"""

from __future__ import annotations

import dataclasses
import itertools
import warnings

import numpy as np

from jaxcal.mesh.identify import Identifiability, identify, identify_ranges, measured_pairs

__all__ = [
    "choose_frame",
    "filter_frame",
    "frame_reach",
    "trilateration_reach",
    "first_complete_epoch",
    "with_auto_config",
]


def _triangle_quality(d: np.ndarray, tri) -> float:
    """4 sqrt(3) area / (sum of squared sides): 1 for an equilateral triangle, 0 for a collinear one."""
    i, j, k = tri
    a, b, c = d[i, j], d[i, k], d[j, k]
    if not np.isfinite([a, b, c]).all():
        return 0.0
    s2 = (a + b + c) * (-a + b + c) * (a - b + c) * (a + b - c)
    area = 0.25 * np.sqrt(max(s2, 0.0))
    den = a * a + b * b + c * c
    return float(4.0 * np.sqrt(3.0) * area / den) if den > 0 else 0.0


def trilateration_reach(adj: np.ndarray, tri, min_refs: int) -> np.ndarray:
    """(N,) bool: the nodes a grid filter started from the frame `tri` can localise, in the order it does
    (a node localises once it has ranged `min_refs` localised nodes; the three frame nodes from the
    frame rule: a1 from a range to a0, a2 from ranges to a0 and a1). Rigidity (`identify`) can fix
    more: a node reached only through a node it ranges alone is rigid in the network but never heard
    by the filter from enough localised neighbours.

    Args:
        adj: (N, N) bool measured pairs (`measured_pairs`). tri: the frame (a0, a1, a2).
        min_refs: localised neighbours a node needs (`PGPParams.min_refs`).
    """
    a = np.asarray(adj, dtype=bool)
    placed = np.zeros(a.shape[0], dtype=bool)
    b0, b1, b2 = tri
    placed[b0] = True
    placed[b1] = a[b0, b1]  # eq. 5: a1 from its range to a0 only
    placed[b2] = placed[b1] and a[b2, b0] and a[b2, b1]  # eq. 6: a2 from a0 and a1
    while True:
        new = ~placed & (a[:, placed].sum(axis=1) >= min_refs)
        if not new.any():
            return placed
        placed |= new


def choose_frame(
    range_m: np.ndarray, dim: int = 2, max_candidates: int = 12, exclude=(), min_refs: int = 0, need=()
) -> tuple[tuple[int, int, int], Identifiability] | None:
    """The best frame triple of a recording: most nodes fixed, then best connected and conditioned.

    Candidates are triples whose three pairs are all measured (so the paper's direct frame rule applies)
    among the `max_candidates` nodes with most measured (epoch, peer) slots. Among those fixing the most
    nodes, the score is: least share of epochs in which one of the three pairs is measured, times the
    triangle's shape quality (`_triangle_quality` of the median ranges; near-collinear frames amplify
    ranging errors), times the triple's mean degree. Order inside the triple: a0 the best connected,
    a1 the partner with the most shared epochs.

    Args:
        range_m: (K, N, N) ranges [m]. dim: 2 or 3.
        max_candidates: how many of the best-connected nodes to combine.
        exclude: triples (as given, any order) not to return.
        min_refs: > 0: for a grid filter: rank first by whether every node of `need` is in the triple's
            `trilateration_reach`, then by the fixed nodes it reaches, before the nodes fixed.
        need: nodes a filter run in the triple's frame must localise (the configuration's frame nodes,
            through which its track is moved back).

    Returns:
        ((a0, a1, a2), its Identifiability), or None when no triple has all three pairs measured.
    """
    r = np.asarray(range_m, dtype=np.float64)
    k, n = r.shape[0], r.shape[1]
    fin = np.isfinite(r)
    both = fin | np.swapaxes(fin, 1, 2)
    share = both.mean(axis=0) if k else np.zeros((n, n))
    np.fill_diagonal(share, 0.0)
    with np.errstate(all="ignore"):
        rs = np.where(fin, r, np.swapaxes(np.where(fin, r, np.nan), 1, 2))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(rs, axis=0) if k else np.full((n, n), np.nan)
    adj = share > 0
    deg = adj.sum(axis=1)
    slots = share.sum(axis=1)
    cand = np.argsort(-slots, kind="stable")[: max(3, max_candidates)]
    excl = {tuple(sorted(t)) for t in exclude}
    best = None
    for tri in itertools.combinations(sorted(cand.tolist()), 3):
        if tri in excl:
            continue
        i, j, l_ = tri
        if not (adj[i, j] and adj[i, l_] and adj[j, l_]):
            continue
        q = _triangle_quality(med, tri)
        if q <= 0.05:
            continue
        a0 = max(tri, key=lambda v: (slots[v], -v))
        rest = [v for v in tri if v != a0]
        a1 = max(rest, key=lambda v: (share[a0, v], -v))
        a2 = next(v for v in rest if v != a1)
        ident = identify(adj, (a0, a1, a2), dim)
        score: tuple = (ident.n_fixed, min(share[i, j], share[i, l_], share[j, l_]) * q * deg[list(tri)].mean())
        if min_refs > 0:
            reach = trilateration_reach(adj, tri, min_refs)
            score = (bool(reach[list(need)].all()), int((reach & ident.fixed).sum()), *score)
        if best is None or score > best[0]:
            best = (score, (a0, a1, a2), ident)
    return None if best is None else (best[1], best[2])


def first_complete_epoch(range_m: np.ndarray, anchors) -> int | None:
    """First epoch by which each of the three frame pairs has been measured at least once (None: never)."""
    r = np.asarray(range_m)
    a0, a1, a2 = anchors
    last = 0
    for i, j in ((a0, a1), (a0, a2), (a1, a2)):
        hit = np.flatnonzero(np.isfinite(r[:, i, j]) | np.isfinite(r[:, j, i]))
        if hit.size == 0:
            return None
        last = max(last, int(hit[0]))
    return last


def filter_frame(range_m: np.ndarray, anchors, early: float = 0.05, min_refs: int = 3) -> tuple[int, int, int]:
    """The frame a grid filter (pgp, parametric) should run in, before its track is moved to `anchors`.

    The configuration's own frame when its three pairs (a0-a1, a0-a2, a1-a2) have all been measured
    within the first `early` share of the epochs (the paper's rule: a1 from its range to a0, eq. 5; a2
    from a0 and a1, eq. 6) and the filter reaches from it (`trilateration_reach` with `min_refs`) as many
    of the nodes the ranges fix as from any other triple. Otherwise (a frame pair never or only late
    measured; a frame node that no other node hears; a frame with a mirror image) the triple of
    `choose_frame` from which the filter reaches the configuration's frame nodes (when that frame is
    determined: the caller moves every epoch into it through the estimates of a0, a1, a2 there) and the
    most fixed nodes.

    Args:
        range_m: (K, N, N) ranges [m]. anchors: the configuration (a0, a1, a2).
        early: share of the epochs within which the frame pairs must have been measured.
        min_refs: localised neighbours the filter needs to localise a node (`PGPParams.min_refs`).

    Returns:
        (b0, b1, b2) to run the filter in (`anchors` itself when the paper's rule applies).
    """
    anchors = tuple(int(a) for a in anchors)
    k = np.asarray(range_m).shape[0]
    own = identify_ranges(range_m, anchors)
    best = choose_frame(range_m, min_refs=min_refs, need=anchors if own.frame_fixed else ())
    if best is None:
        return anchors
    tri, ident = best
    adj = measured_pairs(range_m)
    reach_own = int((trilateration_reach(adj, anchors, min_refs) & own.fixed).sum())
    reach_tri = int((trilateration_reach(adj, tri, min_refs) & ident.fixed).sum())
    if reach_tri > reach_own:
        return tri
    first = first_complete_epoch(range_m, anchors)
    if first is not None and first <= max(early * k, 1):
        return anchors
    if not own.frame_fixed:  # no frame to move the track into: the configuration's own, masked later
        return anchors
    tri_first = first_complete_epoch(range_m, tri)
    if first is not None and tri_first is not None and first <= tri_first:
        return anchors
    return tri


def frame_reach(range_m: np.ndarray, tri, min_refs: int = 3) -> tuple[int, int]:
    """(nodes the ranges fix in the frame `tri`, of them those a grid filter started there reaches)."""
    ident = identify_ranges(range_m, tri)
    reach = trilateration_reach(measured_pairs(range_m), tri, min_refs)
    return ident.n_fixed, int((reach & ident.fixed).sum())


def with_auto_config(dataset):
    """`dataset` with a configuration named `auto`: the triple `choose_frame` picks (unless the dataset
    already has one of that name). Returns (dataset, (a0, a1, a2)); raises `JaxcalError` when no triple
    has all three pairs measured."""
    from jaxcal.errors import JaxcalError

    table = dict(dataset.configs)
    if "auto" in table:
        return dataset, tuple(table["auto"])
    best = choose_frame(dataset.range)
    if best is None:
        raise JaxcalError(f"{dataset.name}: --config auto: no three nodes range each other")
    table["auto"] = best[0]
    return dataclasses.replace(dataset, configs=table), best[0]
