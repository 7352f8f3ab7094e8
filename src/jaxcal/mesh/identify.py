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

`identify` is pure NumPy/SciPy on an (N, N) graph (no ranges needed beyond which pairs were measured);
`apply` turns its answer into NaN rows of a `Result` (CONTRACT: NaN row = no estimate) and one warning
line (logger "jaxcal") that names every node left out and why. `choose_frame` ranks triples for
`--config auto`.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
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
    "choose_frame",
    "apply",
    "describe",
    "mask_result",
    "undetermined_frame_result",
    "with_auto_config",
    "filter_frame",
    "frame_reach",
    "trilateration_reach",
    "first_complete_epoch",
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
        import warnings

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


def describe(ident: Identifiability, ids, method: str = "", suggestion=None) -> str | None:
    """One warning line naming the frame's missing links and every node not fixed, and why; None when
    every node is fixed. `suggestion`: an optional ((a0, a1, a2), n_fixed) to propose."""
    ids = [str(v) for v in ids]
    n = len(ids)
    bad = np.flatnonzero(~ident.fixed)
    if bad.size == 0:
        return None
    head = f"{method}: " if method else ""
    parts = []
    a = ident.anchors
    frame = "/".join(ids[v] for v in a)
    if ident.mirror:
        parts.append(f"frame ({frame}) has a mirror image ({ident.mirror}): the other nodes have two placements")
    elif not ident.frame_fixed:
        links = ", ".join(f"{ids[i]}-{ids[j]}" for i, j in ident.missing_frame_links)
        parts.append(f"frame ({frame}) not determined by the ranges" + (f" (never ranged: {links})" if links else ""))
    why = [ident.reason[i] for i in bad if ident.reason[i] != FRAME_UNDETERMINED]
    placed = n - bad.size
    msg = f"{head}{bad.size} of {n} nodes cannot be placed ({_names(bad, ids)}); {placed} fixed"
    if parts:
        msg += "; " + "; ".join(parts)
    if why:
        msg += "; " + "; ".join(why)
    if suggestion is not None:
        tri, nf = suggestion
        if nf > placed:
            msg += f"; suggested frame {ids[tri[0]]}/{ids[tri[1]]}/{ids[tri[2]]} (--config auto) fixes {nf}/{n}"
    return msg


def apply(result, ident: Identifiability, method: str | None = None, warn: bool = True, suggest_from=None):
    """NaN rows (position, covariance, track) for every node `ident` does not fix; one warning line.

    Args:
        result: a `jaxcal.data.Result` in the frame of `ident.anchors`.
        ident: from `identify`.
        method: name used in the warning (default `result.method`).
        warn: log the warning line (logger "jaxcal") when a node is left out.
        suggest_from: (K, N, N) ranges to propose a better frame from (`choose_frame`) when this one is
            not determined; None: no suggestion.

    Returns:
        The `Result` with the unfixed rows set to NaN (the same object when nothing changes).
    """
    bad = ~ident.fixed
    if bad.any():
        pos = np.array(result.position, dtype=np.float64, copy=True)
        pos[bad] = np.nan
        changes = {"position": pos}
        if result.covariance is not None:
            cov = np.array(result.covariance, dtype=np.float64, copy=True)
            cov[bad] = np.nan
            changes["covariance"] = cov
        if result.track_position is not None:
            tr = np.array(result.track_position, dtype=np.float64, copy=True)
            tr[:, bad] = np.nan
            changes["track_position"] = tr
        result = dataclasses.replace(result, **changes)
        if warn:
            sug = None
            if suggest_from is not None and not ident.frame_fixed:
                best = choose_frame(suggest_from, ident.dim)
                sug = None if best is None else (best[0], best[1].n_fixed)
            line = describe(ident, result.ids, method or result.method, sug)
            if line:
                logging.getLogger("jaxcal").warning("%s", line)
    missing = ident.fixed & ~np.isfinite(np.asarray(result.position, dtype=np.float64)).all(axis=1)
    if warn and missing.any():  # the ranges fix them, the method did not place them: say so
        ids = [str(v) for v in result.ids]
        logging.getLogger("jaxcal").warning(
            "%s: %d of the %d nodes the ranges fix left unplaced by the method (%s)",
            method or result.method,
            int(missing.sum()),
            int(ident.fixed.sum()),
            _names(np.flatnonzero(missing), ids),
        )
    return result


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


def mask_result(result, range_m: np.ndarray, warn: bool = True):
    """`apply` with the identifiability of `result`'s own frame and dimension from (K, N, N) ranges: the
    post-step every mesh method ends with. Returns the masked `Result`."""
    anchors = result.frame_anchors()
    if anchors is None:
        return result
    ident = identify_ranges(range_m, anchors, int(result.position.shape[1]), ids=result.ids)
    return apply(result, ident, warn=warn, suggest_from=range_m)


def undetermined_frame_result(dataset, anchors, method: str, dim: int = 2, params=None):
    """A `Result` for a method that needs the whole frame (batch) when the ranges do not determine it:
    a0 at the origin, every other row NaN (one warning line from `mask_result`); None when the frame is
    determined and the method should run."""
    from jaxcal.data import Result

    ident = identify_ranges(dataset.range, anchors, dim, ids=dataset.node_ids)
    if ident.frame_fixed:
        return None
    pos = np.full((dataset.n_nodes, dim), np.nan)
    pos[anchors[0]] = 0.0
    res = Result(
        ids=dataset.node_ids,
        position=pos,
        method=method,
        dataset=dataset.name,
        frame="anchors:{},{},{}".format(*anchors),
        params=dict(params or {}),
    )
    return apply(res, ident, suggest_from=dataset.range)


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
