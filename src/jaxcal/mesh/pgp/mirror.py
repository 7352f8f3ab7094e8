"""Mirror-locked parts of a filter's layout (issue #24): found after the filter, reflected back, or left
unplaced when the ranges cannot tell the two images apart.

A node that localises early on the wrong side of two neighbours' line (its first ranges fit both images)
drags the nodes that localise from it to that side too; the motion update's `top_k` cells and the
hypothesis-weighted likelihood of eq. 10-11 then keep the whole part there, since each of its nodes is
consistent with its neighbours' top cells (they moved with it) and the few ranges across the hinge are
outvoted. The filter cannot leave that mode, so the check runs on its output: the layout is compared, by
the robust (Cauchy) cost of the pair medians, with each *rigid part reflected through a hinge line*:

- hinge lines: the lines through the two nodes of a measured pair;
- parts: on each side of a hinge line, the connected components of the measured graph among that side's
  nodes (the part a flip moves as a whole), and single nodes reflected through the line of two of their
  neighbours.

A reflection keeps every range inside the part and to the hinge nodes, so only the ranges across it
decide. The best reflection is kept while it lowers the cost by more than `margin` (log 19: the Cauchy
cost is the negative log likelihood of the pair medians up to a constant, so the kept image is at least
19 times as likely), both layouts polished first (`pair_covariance.polish`: the filter's cells and lag
are not the ranges' optimum). Nodes that some reflection moves at a cost rise below `margin` have two
images the ranges do not tell apart (a rigid part hinged on two nodes): they are returned as ambiguous,
and `with_pair_covariance` widens their covariance over both images with one warning line
(`span_undecided`).

Cost: host-side NumPy after the filter (not in the scan): one cost per candidate over the pairs, and a
few polishes of the N-node layout."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "MARGIN",
    "Flip",
    "MirrorCheck",
    "candidate_flips",
    "check_mirrors",
    "reflect",
    "resolve_mirrors",
    "robust_cost",
    "span_undecided",
]

MARGIN = math.log(19.0)
"""Cost difference [nats] under which two images count as undecided (a likelihood ratio below 19)."""


@dataclass(frozen=True)
class Flip:
    """One reflection: the nodes `part` ((N,) bool) reflected through the line of nodes `p`, `q`."""

    p: int
    q: int
    part: np.ndarray


@dataclass(frozen=True)
class MirrorCheck:
    """What `check_mirrors` found.

    Attributes:
        position: (N, 2) the input, but nodes the kept moves placed elsewhere (`moved`) at their position in
            `fit` plus the input's offset from the fit of its own image (none where that exceeds `same_m`).
        fit: (N, 2) the ranges' polished fit of the kept image (a2 at y >= 0).
        moves: the moves applied, in order: a `Flip`, or "refit" (the MDS-started fit, `mds_start`).
        moved: (N,) bool, nodes the kept moves placed elsewhere (by more than `same_m`).
        ambiguous: (N,) bool, nodes with a second image within `margin` of the kept one.
        spread: (N, 2, 2) [m^2] the sum over those images of d d^T, d a node's move to the image (0 elsewhere).
        gain: cost decrease [nats] of each applied move; `rival`: the smallest cost rise of a distinct
            image that moves an ambiguous node (inf when none).
    """

    position: np.ndarray
    fit: np.ndarray
    moves: tuple[Flip | str, ...]
    moved: np.ndarray
    ambiguous: np.ndarray
    spread: np.ndarray
    gain: tuple[float, ...]
    rival: float


def robust_cost(x: np.ndarray, i: np.ndarray, j: np.ndarray, z: np.ndarray, scale: float) -> np.ndarray:
    """Cauchy cost sum log(1 + (e / scale)^2) of the pair residuals e = |x_i - x_j| - z, over the last axis
    of pairs; `x` (..., N, 2) gives one cost per leading index."""
    e = np.linalg.norm(x[..., i, :] - x[..., j, :], axis=-1) - z
    return np.sum(np.log1p((e / scale) ** 2), axis=-1)


def reflect(x: np.ndarray, part: np.ndarray, p: int, q: int) -> np.ndarray:
    """`x` (..., N, 2) with the nodes of `part` reflected through the line of nodes p, q (per leading
    index, e.g. per epoch of a track); NaN where p or q is NaN."""
    a, b = x[..., p, :], x[..., q, :]
    d = (b - a) / np.linalg.norm(b - a, axis=-1, keepdims=True)
    v = x - a[..., None, :]
    along = np.sum(v * d[..., None, :], axis=-1, keepdims=True)
    mirrored = a[..., None, :] + 2.0 * along * d[..., None, :] - v
    return np.where(part[:, None], mirrored, x)


def _components(adj: np.ndarray, nodes: np.ndarray) -> list[np.ndarray]:
    """Connected components (index arrays) of the graph `adj` restricted to `nodes`."""
    from scipy.sparse.csgraph import connected_components  # noqa: PLC0415

    if nodes.size == 0:
        return []
    _, lab = connected_components(adj[np.ix_(nodes, nodes)], directed=False)
    return [nodes[lab == c] for c in range(lab.max() + 1)]


def candidate_flips(x: np.ndarray, adj: np.ndarray, anchors, min_sep_m: float = 0.5) -> list[Flip]:
    """Every reflection `check_mirrors` tries (module docstring), none of which moves a0 or a1 (a part
    holding either is replaced by the rest of that line's nodes: the same layout up to a reflection of
    the whole).

    Args:
        x: (N, 2) layout [m], NaN rows = unplaced (never moved, never a hinge).
        adj: (N, N) bool, measured pairs.
        anchors: (a0, a1, a2).
        min_sep_m: hinge nodes closer than this give no line.
    """
    n = x.shape[0]
    placed = np.isfinite(x).all(axis=1)
    a01 = np.zeros(n, dtype=bool)
    a01[list(anchors[:2])] = True
    seen: set[bytes] = set()
    out: list[Flip] = []

    def add(p, q, part):
        if (part & a01).any():
            part = placed & ~part
            part[[p, q]] = False
            if (part & a01).any():
                return
        key = part.tobytes()
        if part.any() and key not in seen:
            seen.add(key)
            out.append(Flip(int(p), int(q), part))

    ps, qs = np.nonzero(np.triu(adj & placed[:, None] & placed[None, :], 1))
    for p, q in zip(ps, qs, strict=True):
        u = x[q] - x[p]
        if np.hypot(*u) < min_sep_m:
            continue
        v = x - x[p]
        side = np.sign(u[0] * v[:, 1] - u[1] * v[:, 0])
        for s in (-1.0, 1.0):
            for comp in _components(adj, np.flatnonzero(placed & (side == s))):
                part = np.zeros(n, dtype=bool)
                part[comp] = True
                add(p, q, part)
    for k in np.flatnonzero(placed):  # single nodes through the line of two of their neighbours
        nb = np.flatnonzero(adj[k] & placed)
        for m, p in enumerate(nb):
            for q in nb[m + 1 :]:
                if np.hypot(*(x[q] - x[p])) >= min_sep_m:
                    part = np.zeros(n, dtype=bool)
                    part[k] = True
                    add(p, q, part)
    return out


def _free(placed: np.ndarray, anchors) -> np.ndarray:
    """Flat indices of the free coordinates of the placed nodes (a0 fixed, a1 on the x axis)."""
    keep = np.repeat(placed, 2)
    keep[2 * anchors[0] : 2 * anchors[0] + 2] = False
    keep[2 * anchors[1] + 1] = False
    return np.flatnonzero(keep)


def check_mirrors(
    x: np.ndarray,
    z_med: np.ndarray,
    anchors,
    scale: float,
    margin: float = MARGIN,
    rounds: int = 4,
    polish_top: int = 4,
    same_m: float = 1.0,
    far_m: float = 5.0,
) -> MirrorCheck:
    """Move mirror-locked parts of a 2-D layout to their other image and mark the nodes whose image is
    undecided (module docstring).

    Args:
        x: (N, 2) the filter's layout in the frame of `anchors` [m]; NaN rows = unplaced.
        z_med: (N, N) pair medians of the ranges [m] (NaN = never measured).
        anchors: (a0, a1, a2) of `x`'s frame.
        scale: Cauchy scale [m] (the filter's `sigma_r`).
        margin: cost difference [nats] a move must win by (module docstring).
        rounds: at most this many moves applied.
        polish_top: distinct reflections (the lowest unpolished costs first) compared after polishing.
        same_m: a polished candidate within this of the polished layout, every node, is the same image.
        far_m: a node this far from the fit of its own layout's image takes the fit (half the filter's
            10 m window: beyond it the distance is no cell or lag error of the filter).

    Returns:
        `MirrorCheck`.
    """
    from jaxcal.mesh.pair_covariance import mds_start, polish  # noqa: PLC0415

    x = np.asarray(x, dtype=np.float64)
    n = x.shape[0]
    placed = np.isfinite(x).all(axis=1)
    z = np.asarray(z_med, dtype=np.float64)
    adj = np.isfinite(z) & np.isfinite(z.T) & ~np.eye(n, dtype=bool)
    iu, ju = np.nonzero(np.triu(adj & placed[:, None] & placed[None, :], 1))
    zz = 0.5 * (z[iu, ju] + z[ju, iu])
    free = _free(placed, anchors)
    none = np.zeros(n, dtype=bool)
    if iu.size == 0 or placed.sum() < 4 or not placed[list(anchors[:2])].all():
        return MirrorCheck(x, x, (), none, none, np.zeros((n, 2, 2)), (), math.inf)
    flip_y = np.array([1.0, -1.0])

    def polished(y):  # the ranges' local optimum from y (a2 in y >= 0) and its cost
        w = polish(np.where(placed[:, None], y, 0.0), iu, ju, zz, free, scale)
        w = w * flip_y if w[anchors[2], 1] < 0 else w
        return np.where(placed[:, None], w, np.nan), float(robust_cost(w, iu, ju, zz, scale))

    def apart(w, at):  # (N,) nodes of w more than same_m from `at`
        return np.where(placed, np.linalg.norm(w - at, axis=1), 0.0) > same_m

    def rivals(at, first):  # distinct images of the polished layout `at`: (move, polished layout, cost)
        out = []
        cands = candidate_flips(at, adj, anchors)
        if cands:
            ys = np.stack([reflect(at, c.part, c.p, c.q) for c in cands])
            raw = robust_cost(np.where(placed[:, None], ys, 0.0), iu, ju, zz, scale)
            for t in np.argsort(raw)[: 3 * polish_top]:
                w, cost = polished(ys[t])
                if apart(w, at).any():
                    out.append((cands[t], w, cost))
                    if len(out) == polish_top:
                        break
        start = mds_start(at, iu, ju, zz, anchors) if first else None
        if start is not None:
            w, cost = polished(start)
            if apart(w, at).any():
                out.append(("refit", w, cost))
        return out

    moves: list[Flip | str] = []
    gains: list[float] = []
    at0, base = polished(x)
    at = at0
    found = rivals(at, True)
    for _ in range(rounds):
        if not found or min(f[2] for f in found) - base >= -margin:
            break
        move, at, cost = min(found, key=lambda f: f[2])
        moves.append(move)
        gains.append(base - cost)
        base = cost
        found = rivals(at, False)
    ambiguous = np.zeros(n, dtype=bool)
    spread = np.zeros((n, 2, 2))
    rival = math.inf
    for _, w, cost in found:
        if cost - base < margin:
            far = apart(w, at)
            ambiguous |= far
            d = np.where(far[:, None], w - at, 0.0)
            spread += d[:, :, None] * d[:, None, :]
            rival = min(rival, cost - base)
    # a moved node keeps the filter's own offset from the ranges' fit (its cells, its lag): the network
    # displacement term of `with_pair_covariance` measures that error, and a node placed on the fit itself
    # would report none (weak seed 11, every node moved: coverage 100 % -> 57 % at the fit). An offset
    # beyond same_m is no such error (the polish itself left the filter's place, weaknodes seed 0
    # parametric: 22 m): that node takes the fit.
    # A node more than far_m from the fit of the filter's own image (its polish alone left the filter's
    # place: nlos seed 0 parametric, 22 m) is not in that image at all: it takes the fit even without a move.
    off = x - at0
    dist = np.where(placed, np.linalg.norm(off, axis=1), 0.0)
    off = np.where((dist > same_m)[:, None], 0.0, off)
    y = at + off
    moved = apart(y, x) if moves else dist > far_m
    y = np.where(moved[:, None], y, x)
    return MirrorCheck(y, at, tuple(moves), moved, ambiguous, spread, tuple(gains), rival)


def resolve_mirrors(
    range_m: np.ndarray, ids, anchors, final: np.ndarray, cov: np.ndarray, scale: float, method: str = "pgp"
) -> tuple[np.ndarray, np.ndarray]:
    """A filter run's final layout after `check_mirrors`, as `run_pgp` reports it.

    Nodes a kept move placed elsewhere take their position in the ranges' fit of the kept image plus their
    offset from the fit of the filter's image (`MirrorCheck.position`; their grid covariance is kept:
    `with_pair_covariance` replaces it where the pairs fix the node, and widens it over an undecided
    image, `span_undecided`). A move is one log line (logger "jaxcal", info).

    Args:
        range_m: (K, N, N) ranges [m]. ids: (N,) node ids. anchors: (a0, a1, a2) of `final`'s frame.
        final: (N, 2) the filter's final positions [m]. cov: (N, 2, 2) their covariances [m^2].
        scale: Cauchy scale [m] (`sigma_r`). method: the name in the log lines.

    Returns:
        (final, cov), new arrays.
    """
    import logging  # noqa: PLC0415

    final, cov = np.array(final, dtype=np.float64), np.array(cov, dtype=np.float64)
    if final.shape[1] != 2:
        return final, cov
    mc = check_mirrors(final, _medians(range_m), anchors, scale)
    log = logging.getLogger("jaxcal")

    def names(mask):
        return ", ".join(ids[k] for k in np.flatnonzero(mask))

    if mc.moved.any():
        how = "; ".join(m if isinstance(m, str) else f"reflection through {ids[m.p]}-{ids[m.q]}" for m in mc.moves)
        log.info(
            "%s: %s moved to the ranges' fit (%s)",
            method,
            names(mc.moved),
            f"a mirror image the ranges reject: robust cost {sum(mc.gain):.1f} nats lower after {how}"
            if mc.moves
            else "more than 5 m from the ranges' fit of the filter's layout",
        )
        final[mc.moved] = mc.position[mc.moved]
    return final, cov


def _medians(range_m: np.ndarray) -> np.ndarray:
    """(N, N) pair medians of (K, N, N) ranges, the two directions of a pair averaged per epoch first."""
    from jaxcal.mesh.pgp.setup import symmetric_ranges  # noqa: PLC0415
    from jaxcal.mesh.range_offset import pair_medians  # noqa: PLC0415

    return pair_medians(symmetric_ranges(np.asarray(range_m, dtype=np.float64)))


def span_undecided(
    range_m: np.ndarray, ids, anchors, position: np.ndarray, cov: np.ndarray, scale: float, method: str = "pgp"
) -> np.ndarray:
    """`cov` widened, for every node the ranges fix (`identify`) but whose image they leave undecided
    (`check_mirrors`, no move), by d d^T summed over the undecided images (d the node's move to the image):
    the 95 % ellipse then holds both places, each with the node's own width (the other at NEES <= 1 along
    d), so such a node is never reported confidently. One warning line (logger "jaxcal") names them.

    Args:
        range_m: (K, N, N) ranges [m]. ids: (N,) node ids. anchors: (a0, a1, a2) of `position`'s frame.
        position: (N, 2) the reported layout [m]. cov: (N, 2, 2) its covariance [m^2].
        scale: Cauchy scale [m] (`sigma_r`). method: the name in the log line.

    Returns:
        (N, 2, 2) a new array.
    """
    import logging  # noqa: PLC0415

    from jaxcal.mesh.identify import identify_ranges  # noqa: PLC0415

    cov = np.array(cov, dtype=np.float64)
    if position.shape[1] != 2:
        return cov
    mc = check_mirrors(position, _medians(range_m), anchors, scale, rounds=0)
    ok = np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(position).all(axis=1)
    undecided = mc.ambiguous & identify_ranges(range_m, anchors, ids=ids).fixed & ok
    if undecided.any():
        cov[undecided] = cov[undecided] + mc.spread[undecided]
        logging.getLogger("jaxcal").warning(
            "%s: %s have two images the ranges do not tell apart (cost difference %.1f < %.1f nats): their "
            "covariance spans both",
            method,
            ", ".join(ids[k] for k in np.flatnonzero(undecided)),
            mc.rival,
            MARGIN,
        )
    return cov
