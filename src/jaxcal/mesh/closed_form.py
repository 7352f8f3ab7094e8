"""Closed-form (CF) baseline of the grid paper, Section II-B: one independent 2-D fix per epoch.

Per epoch k, with z_ij the measured distance (the mean of i->j and j->i when both exist):

1. Frame, eqs. (1)-(2): a0 = (0, 0); a1 = (z_01, 0); a2 = (x2, sqrt(z_02^2 - x2^2)) with
   x2 = (z_02^2 - z_12^2 + x1^2) / (2 x1). A missing z_01 leaves the whole epoch empty; a missing
   z_02 / z_12 or a negative radicand leaves a2 (and hence every later node) empty.
2. Placement rule for every other node, in rounds: in each round, every node not yet placed whose
   *references* (nodes placed in an earlier round with a measured distance to it) number at least
   `min_refs` (>= 3) and are well spread (the ratio of the smaller to the larger principal standard
   deviation of the reference positions is at least `min_spread_ratio`, i.e. they are not nearly
   collinear; a ratio, so the rule is the same in a 5 m room and a 50 m hall) is placed by linear least
   squares over all its references: subtracting the mean of the circle equations |x - p_j|^2 = z_j^2
   gives 2 (p_j - p_mean) . (x - p_mean) = |p_j - p_mean|^2 - z_j^2 - mean(...), solved by the 2 x 2
   normal equations. Rounds repeat until no node is added (at most N - 3 rounds). With
   `anchors_only=True` the references are a0, a1, a2 only (the stricter rule the paper's Fig. 10
   discusses: a node whose range to a1 is missing is never placed).
   Anything not placeable is NaN for that epoch, never an error.
   Beyond the paper: an epoch whose own frame cannot be built (a missing a0-a1, a0-a2 or a1-a2 range)
   is placed in another well-connected frame by the same rule and moved into the configuration's frame
   through its placed a0, a1, a2 (`_proxy`), so a frame pair that never ranges does not leave the whole
   track empty (issue #18); when most epochs lack their own frame, the final positions are the proxy
   frame's medians moved through the median a0, a1, a2. The same proxy serves an epoch whose own
   frame is built but whose rule stalls (a node hears >= 3 nodes yet stays unplaced: a thin a0-a1-a2
   triangle fails the spread test, so nothing beyond the frame is placed): where the proxy's epoch,
   moved into the configuration's frame, places more nodes, it replaces the own epoch (not with
   `anchors_only`, the paper's strict rule). Other epochs with their own frame are unchanged.
   Nodes the measured graph cannot fix at all (`identify.py`) are NaN rows, with one warning line.
3. The final position of a node is the component-wise median of its per-epoch fixes (robust to the
   NLOS outlier epochs); NaN when it was never placed. The result keeps the per-epoch track, so the
   availability of a node (Fig. 10) is the fraction of epochs with a fix.

The per-epoch kernel is written for one distance matrix and `jax.vmap`-ped over epochs inside one
`jax.jit`; parameters are traced arrays, so changing them does not recompile.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxcal.data import MeshDataset, Result
from jaxcal.errors import JaxcalError
from jaxcal.params import as_dict, with_overrides

__all__ = ["ClosedFormParams", "symmetrise", "place_epochs", "calibrate"]


class ClosedFormParams(eqx.Module):
    """Parameters of the closed-form baseline.

    Attributes:
        min_refs: least number of placed references a node needs (>= 3: two give a mirror ambiguity).
        min_spread_ratio: least ratio of the smaller to the larger principal standard deviation of
            the reference positions (0: any non-collinear set; 1: only isotropic sets); guards against
            near-collinear references, which amplify ranging errors along the thin axis.
        anchors_only: use only a0, a1, a2 as references (the paper's stricter dependency on a1).
    """

    min_refs: int = 3
    min_spread_ratio: float = 0.1
    anchors_only: bool = False


def symmetrise(ranges: np.ndarray) -> np.ndarray:
    """(K, N, N) ranges -> symmetric distances: mean of i->j and j->i where both exist, else the one
    that exists, else NaN."""
    r = np.asarray(ranges, dtype=np.float64)
    rt = np.swapaxes(r, 1, 2)
    both = np.isfinite(r) & np.isfinite(rt)
    out = np.where(np.isfinite(r), r, rt)
    return np.where(both, 0.5 * (r + rt), out)


def _place_one_epoch(
    d: Float[Array, "n n"],  # noqa: F722
    anchors: Int[Array, "3"],  # noqa: F722, UP037
    min_refs: Float[Array, ""],  # noqa: F722
    min_ratio: Float[Array, ""],  # noqa: F722
    anchors_only: Bool[Array, ""],  # noqa: F722
) -> Float[Array, "n 2"]:  # noqa: F722
    n = d.shape[0]
    a0, a1, a2 = anchors[0], anchors[1], anchors[2]
    idx = jnp.arange(n)
    nan = jnp.array(jnp.nan, d.dtype)

    # eqs. (1)-(2)
    x1 = d[a0, a1]
    ok1 = jnp.isfinite(x1) & (x1 > 0)
    x1s = jnp.where(ok1, x1, 1.0)
    z02, z12 = d[a0, a2], d[a1, a2]
    x2 = (z02**2 - z12**2 + x1s**2) / (2 * x1s)
    rad = z02**2 - x2**2
    ok2 = ok1 & jnp.isfinite(rad) & (rad >= 0)
    y2 = jnp.sqrt(jnp.where(ok2, rad, 0.0))

    pos = jnp.full((n, 2), nan)
    pos = pos.at[a0].set(jnp.where(ok1, jnp.zeros(2, d.dtype), nan))
    pos = pos.at[a1].set(jnp.where(ok1, jnp.stack([x1s, jnp.zeros((), d.dtype)]), nan))
    pos = pos.at[a2].set(jnp.where(ok2, jnp.stack([x2, y2]), nan))
    is_anchor = (idx == a0) | (idx == a1) | (idx == a2)
    dz = jnp.where(jnp.isfinite(d), d, 0.0)

    def one_round(_, pos):
        placed = jnp.isfinite(pos).all(axis=1)
        ref_ok = placed & jnp.where(anchors_only, is_anchor, True)
        w = ref_ok[None, :] & jnp.isfinite(d) & (idx[:, None] != idx[None, :])  # (node i, ref j)
        wf = w.astype(d.dtype)
        m = wf.sum(axis=1)
        ms = jnp.maximum(m, 1.0)
        p = jnp.where(placed[:, None], pos, 0.0)  # (j, 2)
        pbar = (wf @ p) / ms[:, None]  # (i, 2)
        q = p[None, :, :] - pbar[:, None, :]  # (i, j, 2) references centred per node
        c = jnp.sum(q * q, axis=-1) - dz**2
        cbar = jnp.sum(wf * c, axis=1) / ms
        b = c - cbar[:, None]
        a = 2.0 * q
        mat = jnp.einsum("ij,ijk,ijl->ikl", wf, a, a)
        vec = jnp.einsum("ij,ijk,ij->ik", wf, a, b)
        # spread: principal variances of the references (eigenvalues of their covariance, mat / 4m)
        cov = mat / (4.0 * ms[:, None, None])
        tr2 = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
        det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2
        root = jnp.sqrt(jnp.maximum(tr2**2 - det, 0.0))
        lam_min, lam_max = tr2 - root, tr2 + root
        good = (~placed) & (m >= min_refs) & (lam_min >= min_ratio**2 * lam_max) & (lam_min > 0)
        detm = jnp.where(good, mat[:, 0, 0] * mat[:, 1, 1] - mat[:, 0, 1] ** 2, 1.0)
        y0 = (mat[:, 1, 1] * vec[:, 0] - mat[:, 0, 1] * vec[:, 1]) / detm
        y1 = (mat[:, 0, 0] * vec[:, 1] - mat[:, 1, 0] * vec[:, 0]) / detm
        new = pbar + jnp.stack([y0, y1], axis=1)
        return jnp.where(good[:, None], new, pos)

    return jax.lax.fori_loop(0, max(n - 3, 0), one_round, pos)


@jax.jit
def _place_all(d, anchors, min_refs, min_ratio, anchors_only):
    return jax.vmap(_place_one_epoch, in_axes=(0, None, None, None, None))(
        d, anchors, min_refs, min_ratio, anchors_only
    )


def place_epochs(
    distances: np.ndarray, anchors: tuple[int, int, int], params: ClosedFormParams | None = None
) -> np.ndarray:
    """Closed-form fixes of every node at every epoch.

    Args:
        distances: (K, N, N) symmetric distances [m] (see `symmetrise`), NaN where missing.
        anchors: (a0, a1, a2) node indices defining the frame.
        params: placement rule; `ClosedFormParams()` when None.

    Returns:
        (K, N, 2) positions [m] in the anchor frame; NaN where a node could not be placed.
    """
    p = ClosedFormParams() if params is None else params
    if int(p.min_refs) < 3:
        raise JaxcalError(f"parameter min_refs: must be at least 3, got {p.min_refs}")
    if not 0.0 <= float(p.min_spread_ratio) <= 1.0:
        raise JaxcalError(f"parameter min_spread_ratio: must lie in [0, 1], got {p.min_spread_ratio}")
    d = jnp.asarray(distances)
    if d.shape[0] == 0:
        return np.zeros((0, d.shape[1], 2))
    out = _place_all(
        d,
        jnp.asarray(anchors, dtype=jnp.int32),
        jnp.asarray(float(p.min_refs), d.dtype),
        jnp.asarray(float(p.min_spread_ratio), d.dtype),
        jnp.asarray(bool(p.anchors_only)),
    )
    return np.asarray(out, dtype=np.float64)


def _proxy(range_m, dist, track, anchors, p: ClosedFormParams, n_proxy: int = 3):
    """Track and final positions from other frames where the configuration's own cannot be built.

    Up to `n_proxy` well-connected triples (`frame_choice.choose_frame`, best first) are tried: every epoch
    is placed in the triple's frame by the same rule, the per-node medians are taken there, and the
    triple whose medians best reproduce the median ranges of the pairs touching a0, a1, a2 is preferred
    (the frame is only as good as those three nodes). Epochs without their own frame, and own epochs
    whose rule stalled, are moved into the configuration's frame through that epoch's a0, a1, a2
    (`frame.to_frame_track`) from the frame that places the most nodes in that epoch (ties: the own
    frame, then the preferred triple); the final
    positions are the proxy's medians moved through the median a0, a1, a2 (one noisy epoch of a1
    rotates everything, the median does not).

    Returns:
        (track, final or None): final is None when the own frame holds in most epochs (the paper's
        per-node median of the track stands) or no proxy places a0, a1 and a2.
    """
    from jaxcal.mesh.frame import to_frame, to_frame_track
    from jaxcal.mesh.frame_choice import choose_frame

    a0, a1, a2 = anchors
    own = np.isfinite(track[:, [a1, a2]]).all(axis=(1, 2))
    placed = np.isfinite(track).all(axis=2).sum(axis=1)
    # a node with >= 3 measured neighbours in an epoch whose own frame left it unplaced: the own
    # frame's references were too poorly spread (a thin a0-a1-a2 triangle stalls the rule), a
    # well-spread proxy frame may place it
    heard = (np.isfinite(dist).sum(axis=2) >= 3).sum(axis=1)
    stalled = own & (placed < heard) & (not bool(p.anchors_only))  # anchors_only: the paper's strict rule
    if (own & ~stalled).all() or track.shape[0] == 0:
        return track, None
    med_d = _nanmedian(dist)
    near = np.zeros(med_d.shape, dtype=bool)
    near[[a0, a1, a2], :] = True
    near = (near | near.T) & np.isfinite(med_d)
    found_all: list[tuple[float, int, np.ndarray, np.ndarray]] = []  # (median residual, order, track, median)
    tried = [tuple(sorted(anchors))]
    for _ in range(n_proxy):
        found = choose_frame(range_m, exclude=tried)
        if found is None:
            break
        tri = found[0]
        tried.append(tuple(sorted(tri)))
        tr = place_epochs(dist, tri, p)
        med = _nanmedian(tr)
        if not np.isfinite(med[[a0, a1, a2]]).all():
            continue
        dm = np.linalg.norm(med[:, None] - med[None], axis=-1)
        res = np.abs(dm - med_d)[near & np.isfinite(dm)]
        found_all.append((float(np.median(res)) if res.size else np.inf, len(found_all), tr, med))
    if not found_all:
        return track, None
    found_all.sort(key=lambda t: t[:2])
    _, _, tr, med = found_all[0]
    out = track.copy()
    todo = ~own | stalled
    count = np.where(own, placed, -1)[todo]  # nodes placed in each epoch to redo (-1: no own frame)
    for *_, tr_k, _ in found_all:  # per epoch, the frame that places the most nodes (ties: own, best proxy)
        moved = to_frame_track(tr_k[todo], a0, a1, a2)
        n_moved = np.where(
            np.isfinite(moved[:, [a0, a1, a2]]).all(axis=(1, 2)), np.isfinite(moved).all(axis=2).sum(axis=1), -1
        )
        more = n_moved > count
        rows = np.flatnonzero(todo)[more]
        out[rows] = moved[more]
        count = np.where(more, n_moved, count)
    try:
        final = to_frame(med, a0, a1, a2)
    except ValueError:
        final = None
    return out, (None if own.mean() >= 0.5 else final)


def _nanmedian(x: np.ndarray) -> np.ndarray:
    """Median over axis 0 ignoring NaN, NaN where there is no value (without the all-NaN warning)."""
    x = np.asarray(x, dtype=np.float64)
    srt = np.sort(x, axis=0)  # NaN last
    cnt = np.isfinite(x).sum(axis=0)
    lo = np.take_along_axis(srt, np.maximum((cnt - 1) // 2, 0)[None], axis=0)[0]
    hi = np.take_along_axis(srt, np.maximum(cnt // 2, 0)[None], axis=0)[0]
    return np.where(cnt > 0, 0.5 * (lo + hi), np.nan)


def calibrate(
    dataset: MeshDataset,
    params: Mapping[str, Any] | ClosedFormParams | None = None,
    config: str | None = None,
) -> Result:
    """Closed-form calibration of a mesh dataset (registered as method `cf`).

    Args:
        dataset: mesh dataset, ranges (K, N, N).
        params: overrides of `ClosedFormParams` (a mapping, e.g. from `--set`) or a `ClosedFormParams`.
        config: name of the frame configuration (a0, a1, a2); the dataset's default when None.

    Returns:
        Result in frame `anchors:a0,a1,a2` with the (K, N, 2) per-epoch track and the per-node
        median of the track as final position.
    """
    p = params if isinstance(params, ClosedFormParams) else with_overrides(ClosedFormParams(), params)
    anchors = dataset.config(config)
    dist = symmetrise(dataset.range)
    track = place_epochs(dist, anchors, p)
    track, proxy_final = _proxy(dataset.range, dist, track, anchors, p)
    has = np.isfinite(track).all(axis=2)  # (K, N)
    final = np.full((dataset.n_nodes, 2), np.nan)
    for i in np.flatnonzero(has.any(axis=0)):
        final[i] = np.median(track[has[:, i], i], axis=0)
    if proxy_final is not None:
        final = proxy_final
    res = Result(
        ids=dataset.node_ids,
        position=final,
        method="cf",
        dataset=dataset.name,
        frame="anchors:{},{},{}".format(*anchors),
        params={**as_dict(p), "config": config},
        track_time=dataset.time,
        track_position=track,
    )
    from jaxcal.mesh.masking import mask_result

    return mask_result(res, dataset.range)
