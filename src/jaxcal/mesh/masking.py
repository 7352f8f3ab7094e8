"""What a mesh method reports for the nodes the ranges cannot fix: NaN rows and one warning line.

`apply` turns an `identify.Identifiability` into NaN rows of a `Result` (CONTRACT: NaN row = no
estimate) and one warning line (logger "jaxcal", `describe`) that names every node left out and why,
with a better frame (`frame_choice.choose_frame`) when the configured one is not determined.
`mask_result` is the post-step every mesh method ends with; `undetermined_frame_result` is the answer
of a method that needs the whole frame (batch) when the ranges do not determine it.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from jaxcal.mesh.frame_choice import choose_frame
from jaxcal.mesh.identify import FRAME_UNDETERMINED, Identifiability, _names, identify_ranges

__all__ = ["apply", "describe", "mask_result", "undetermined_frame_result"]


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
