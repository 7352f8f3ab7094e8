"""UWB range-zone gating for one-shot place recognition (second paper, Section III-D).

A prior map holds keyframes: a position and one descriptor vector each (from any place-recognition
method). A query brings a descriptor plus UWB ranges to some calibrated anchors (NaN = not heard).
Each heard anchor `a` with range `r_a` admits the keyframes inside its range zone

    | ||p_kf - anchor_a|| - r_a | <= w_a,   w_a = delta + k_sigma * sigma_a + range_rel * r_a,

where `delta` is the paper's bias (it widens the zone boundaries `r_{i-1} - delta <= ||p - a|| <
r_i + delta`), `sigma_a` the anchor's calibration uncertainty (square root of the largest eigenvalue
of its covariance, i.e. its worst direction) and `range_rel * r_a` a width growing with the range.
The zones of several anchors intersect; a query with no usable range falls back to the full search.
Descriptor matching (cosine or L2 distance) then ranks the admissible keyframes.

Three implementations of the same ranking, all for one query and `vmap`ped outward:

- `rank_full`: descriptor matching over the whole database (the ungated baseline).
- `rank_masked`: the zone mask over all keyframes, then a masked top-k; simple, same work as full.
- `rank_indexed`: the fast path. `ZoneIndex` keeps, per anchor, the keyframes sorted by distance to
  it, so a zone is one contiguous slice found by binary search. The anchor with the smallest zone is
  the pivot; its slice (at most `capacity` keyframes) is gathered, the other anchors' zones are
  tested on those candidates only, and only they are matched: work O(A log K + capacity * F)
  instead of
  O(K * F). `search` picks `capacity` per query (powers of two, so few compilations) and is exact.

The sort-based index is an exact continuous version of the paper's discrete range zones ("radii"
r_i with boundaries widened by delta): a zone is looked up by binary search instead of a bucket id.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxcal.errors import InputError

__all__ = [
    "KeyframeDB",
    "Anchors",
    "GateParams",
    "ZoneIndex",
    "Candidates",
    "zone_halfwidth",
    "admissible",
    "rank_full",
    "rank_masked",
    "rank_indexed",
    "zone_counts",
    "search",
    "search_full",
    "search_one",
    "search_one_full",
]

METRICS = ("cosine", "l2")


class KeyframeDB(eqx.Module):
    """A prior map database: keyframe positions and one descriptor per keyframe.

    Attributes:
        position: (K, D) keyframe positions [m], D = 2 or 3.
        descriptor: (K, F) descriptors; unit-normalised rows when `metric` is 'cosine'.
        sq_norm: (K,) squared norms of the descriptors (for the L2 distance).
        metric: 'cosine' (1 - cosine similarity) or 'l2' (Euclidean distance). Static.
    """

    position: Float[Array, "K D"]
    descriptor: Float[Array, "K F"]
    sq_norm: Float[Array, " K"]
    metric: str = eqx.field(static=True)

    @classmethod
    def build(cls, position, descriptor, metric: str = "cosine") -> KeyframeDB:
        """Validate and prepare a database.

        Args:
            position: (K, D) keyframe positions [m], finite.
            descriptor: (K, F) descriptors, finite (kept in their float dtype).
            metric: 'cosine' or 'l2'.

        Returns:
            A `KeyframeDB` (cosine descriptors are normalised once here, not per query).
        """
        pos = jnp.asarray(position)
        desc = jnp.asarray(descriptor)
        if metric not in METRICS:
            raise InputError(f"unknown descriptor metric {metric!r} (known: {', '.join(METRICS)})")
        if pos.ndim != 2 or pos.shape[1] not in (2, 3):
            raise InputError(f"keyframe positions: expected shape (K, 2|3), got {tuple(pos.shape)}")
        if desc.ndim != 2 or desc.shape[0] != pos.shape[0] or desc.shape[1] < 1:
            raise InputError(f"keyframe descriptors: expected shape ({pos.shape[0]}, F), got {tuple(desc.shape)}")
        if pos.shape[0] < 1:
            raise InputError("keyframe database is empty")
        if not (bool(jnp.all(jnp.isfinite(pos))) and bool(jnp.all(jnp.isfinite(desc)))):
            raise InputError("keyframe positions and descriptors must be finite")
        if not jnp.issubdtype(desc.dtype, jnp.floating):
            desc = desc.astype(jnp.float32)
        if metric == "cosine":
            norm = jnp.linalg.norm(desc, axis=1, keepdims=True)
            desc = desc / jnp.where(norm > 0, norm, 1.0)
        return cls(position=pos, descriptor=desc, sq_norm=jnp.sum(desc * desc, axis=1), metric=metric)

    @property
    def n_keyframes(self) -> int:
        return int(self.position.shape[0])


class Anchors(eqx.Module):
    """Calibrated anchors used for gating.

    Attributes:
        position: (A, D) anchor positions [m]; a NaN row: no estimate (never gates).
        sigma: (A,) one-sigma position uncertainty [m] along the worst direction (0 when unknown).
    """

    position: Float[Array, "A D"]
    sigma: Float[Array, " A"]

    @classmethod
    def from_estimate(cls, position, covariance=None) -> Anchors:
        """Anchors from a calibration result.

        Args:
            position: (A, D) estimated positions [m]; NaN rows allowed.
            covariance: (A, D, D) position covariances [m^2], or None (sigma = 0).

        Returns:
            `Anchors` with sigma = sqrt of the largest covariance eigenvalue (NaN covariances -> 0).
        """
        pos = np.asarray(position, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[1] not in (2, 3):
            raise InputError(f"anchor positions: expected shape (A, 2|3), got {pos.shape}")
        if covariance is None:
            sigma = np.zeros(pos.shape[0])
        else:
            cov = np.asarray(covariance, dtype=np.float64)
            if cov.shape != (pos.shape[0], pos.shape[1], pos.shape[1]):
                raise InputError(
                    f"anchor covariances: expected shape {(pos.shape[0],) + pos.shape[1:] * 2}, got {cov.shape}"
                )
            ok = np.all(np.isfinite(cov), axis=(1, 2))
            safe = np.where(ok[:, None, None], cov, 0.0)
            eig = np.linalg.eigvalsh(0.5 * (safe + np.swapaxes(safe, 1, 2)))
            sigma = np.sqrt(np.clip(eig[:, -1], 0.0, None))
        return cls(position=jnp.asarray(pos), sigma=jnp.asarray(sigma))


class GateParams(eqx.Module):
    """Zone-width parameters (arrays, so changing a value never recompiles).

    Attributes:
        delta_m: the paper's bias delta [m]: fixed widening of every zone boundary.
        k_sigma: multiple of the anchor's sigma added to the half-width.
        range_rel: half-width per metre of measured range (range-dependent ranging error).
    """

    delta_m: Float[Array, ""] = eqx.field(default=3.0, converter=jnp.asarray)
    k_sigma: Float[Array, ""] = eqx.field(default=2.0, converter=jnp.asarray)
    range_rel: Float[Array, ""] = eqx.field(default=0.01, converter=jnp.asarray)


class ZoneIndex(eqx.Module):
    """Per anchor, the keyframes sorted by their distance to it (a pre-bucketed zone index).

    Attributes:
        order: (A, K) keyframe indices in increasing distance to anchor a.
        sorted_dist: (A, K) those distances [m]; +inf for an anchor without position.
    """

    order: Int[Array, "A K"]
    sorted_dist: Float[Array, "A K"]

    @classmethod
    def build(cls, db: KeyframeDB, anchors: Anchors) -> ZoneIndex:
        """Sort the keyframes by distance to every anchor (once per database and calibration)."""
        _check_dims(db, anchors)
        d = _distances(db.position, anchors.position)  # (K, A)
        d = jnp.where(jnp.isfinite(d), d, jnp.inf).T
        order = jnp.argsort(d, axis=1).astype(jnp.int32)
        return cls(order=order, sorted_dist=jnp.take_along_axis(d, order, axis=1))


class Candidates(eqx.Module):
    """Ranked candidates of one query (or a batch: every field gains a leading Q axis).

    Attributes:
        index: (k,) keyframe indices, best first; -1 where fewer than k keyframes were admissible.
        distance: (k,) descriptor distances; +inf where index is -1.
        n_admissible: () number of keyframes inside the intersected zones (K for the full search).
    """

    index: Int[Array, " k"]
    distance: Float[Array, " k"]
    n_admissible: Int[Array, ""]


def _check_dims(db: KeyframeDB, anchors: Anchors) -> None:
    if db.position.shape[1] != anchors.position.shape[1]:
        raise InputError(f"keyframes are {db.position.shape[1]}-D but anchors are {anchors.position.shape[1]}-D")


def _distances(points: Float[Array, "N D"], anchors: Float[Array, "A D"]) -> Float[Array, "N A"]:
    diff = points[:, None, :] - anchors[None, :, :]
    return jnp.sqrt(jnp.sum(diff * diff, axis=-1))


def _usable(anchors: Anchors, range_m: Float[Array, " A"]) -> Bool[Array, " A"]:
    """Ranges that gate: finite, non-negative, to an anchor with a position estimate."""
    pos_ok = jnp.all(jnp.isfinite(anchors.position), axis=1)
    return pos_ok & jnp.isfinite(range_m) & (range_m >= 0)


def zone_halfwidth(anchors: Anchors, range_m: Float[Array, " A"], params: GateParams) -> Float[Array, " A"]:
    """Half-width w_a [m] of each anchor's range zone for measured ranges `range_m` (A,) [m]."""
    r = jnp.where(jnp.isfinite(range_m), range_m, 0.0)
    return params.delta_m + params.k_sigma * anchors.sigma + params.range_rel * r


def admissible(db: KeyframeDB, anchors: Anchors, range_m: Float[Array, " A"], params: GateParams) -> Bool[Array, " K"]:
    """Zone mask of one query: keyframes inside every heard anchor's range zone.

    Args:
        db: the keyframe database (K keyframes).
        anchors: A calibrated anchors.
        range_m: (A,) measured ranges [m]; NaN = anchor not heard (does not restrict).
        params: zone widths.

    Returns:
        (K,) bool; all True when no range is usable (full-search fallback).
    """
    use = _usable(anchors, range_m)
    w = zone_halfwidth(anchors, range_m, params)
    d = _distances(db.position, anchors.position)  # (K, A)
    inside = jnp.abs(d - range_m[None, :]) <= w[None, :]
    return jnp.all(inside | ~use[None, :], axis=1)


def _descriptor_distance(db_desc, db_sq, q, metric: str):
    """Distances between a query descriptor (F,) and rows of `db_desc` (C, F)."""
    q = q.astype(db_desc.dtype)
    if metric == "cosine":
        qn = jnp.linalg.norm(q)
        q = q / jnp.where(qn > 0, qn, 1.0)
        return 1.0 - db_desc @ q
    sq = db_sq - 2.0 * (db_desc @ q) + jnp.sum(q * q)
    return jnp.sqrt(jnp.maximum(sq, 0.0))


def _top(dist, valid, index, top_k: int, n_admissible) -> Candidates:
    score = jnp.where(valid, -dist, -jnp.inf)
    neg, pos = jax.lax.top_k(score, top_k)
    ok = jnp.isfinite(neg)
    return Candidates(
        index=jnp.where(ok, index[pos], -1).astype(jnp.int32),
        distance=jnp.where(ok, -neg, jnp.inf),
        n_admissible=jnp.asarray(n_admissible, jnp.int32),
    )


def rank_full(db: KeyframeDB, descriptor: Float[Array, " F"], top_k: int) -> Candidates:
    """Ungated search: the `top_k` (<= K) keyframes nearest in descriptor space to one query."""
    dist = _descriptor_distance(db.descriptor, db.sq_norm, descriptor, db.metric)
    k = db.position.shape[0]
    valid = jnp.ones(k, bool)
    return _top(dist, valid, jnp.arange(k), top_k, k)


def rank_masked(
    db: KeyframeDB,
    anchors: Anchors,
    range_m: Float[Array, " A"],
    descriptor: Float[Array, " F"],
    params: GateParams,
    top_k: int,
) -> Candidates:
    """Gated search by masking: match every keyframe, keep the admissible ones (reference path)."""
    mask = admissible(db, anchors, range_m, params)
    dist = _descriptor_distance(db.descriptor, db.sq_norm, descriptor, db.metric)
    return _top(dist, mask, jnp.arange(db.position.shape[0]), top_k, jnp.sum(mask))


def _pivot_slice(index: ZoneIndex, anchors: Anchors, range_m, params):
    """Per anchor [lo, hi) slice of its sorted keyframes that covers its zone; unheard: [0, K)."""
    k = index.order.shape[1]
    use = _usable(anchors, range_m)
    w = zone_halfwidth(anchors, range_m, params)
    r = jnp.where(use, range_m, 0.0)
    # A hair wider than the zone so that rounding never drops a boundary keyframe; the exact
    # test |d - r| <= w is applied to the gathered candidates afterwards.
    eps = 1e-6 * (1.0 + r + w)
    lo = jax.vmap(lambda s, v: jnp.searchsorted(s, v, side="left"))(index.sorted_dist, r - w - eps)
    hi = jax.vmap(lambda s, v: jnp.searchsorted(s, v, side="right"))(index.sorted_dist, r + w + eps)
    lo = jnp.where(use, lo, 0)
    hi = jnp.where(use, hi, k)
    return lo, hi


def zone_counts(index: ZoneIndex, anchors: Anchors, range_m: Float[Array, " A"], params: GateParams):
    """Size of the smallest (pivot) zone slice of one query: the capacity `rank_indexed` needs."""
    lo, hi = _pivot_slice(index, anchors, range_m, params)
    return jnp.min(hi - lo)


def rank_indexed(
    db: KeyframeDB,
    index: ZoneIndex,
    anchors: Anchors,
    range_m: Float[Array, " A"],
    descriptor: Float[Array, " F"],
    params: GateParams,
    top_k: int,
    capacity: int,
) -> Candidates:
    """Gated search through the zone index: match only the pivot zone's keyframes.

    Args:
        db, index, anchors: database, its `ZoneIndex` for these anchors, the anchors.
        range_m: (A,) ranges [m], NaN = not heard. descriptor: (F,) query descriptor.
        params: zone widths. top_k: candidates to return (static).
        capacity: static number of keyframes gathered; exact when >= `zone_counts(...)`.

    Returns:
        `Candidates`, equal to `rank_masked` whenever capacity suffices.
    """
    k = index.order.shape[1]
    lo, hi = _pivot_slice(index, anchors, range_m, params)
    pivot = jnp.argmin(hi - lo)
    slot = lo[pivot] + jnp.arange(capacity)
    in_slice = slot < hi[pivot]
    idx = index.order[pivot, jnp.clip(slot, 0, k - 1)]
    pos = db.position[idx]
    use = _usable(anchors, range_m)
    w = zone_halfwidth(anchors, range_m, params)
    d = _distances(pos, anchors.position)
    inside = jnp.all((jnp.abs(d - range_m[None, :]) <= w[None, :]) | ~use[None, :], axis=1)
    valid = in_slice & inside
    dist = _descriptor_distance(db.descriptor[idx], db.sq_norm[idx], descriptor, db.metric)
    return _top(dist, valid, idx, top_k, jnp.sum(valid))


@eqx.filter_jit
def _full_batch(db, descriptors, top_k):
    return jax.vmap(rank_full, in_axes=(None, 0, None))(db, descriptors, top_k)


@eqx.filter_jit
def _counts_batch(index, anchors, ranges, params):
    return jax.vmap(zone_counts, in_axes=(None, None, 0, None))(index, anchors, ranges, params)


@eqx.filter_jit
def _indexed_batch(db, index, anchors, ranges, descriptors, params, top_k, capacity):
    return jax.vmap(rank_indexed, in_axes=(None, None, None, 0, 0, None, None, None))(
        db, index, anchors, ranges, descriptors, params, top_k, capacity
    )


def _branch(db, index, anchors, params, top_k, capacity, range_m, descriptor):
    return rank_indexed(db, index, anchors, range_m, descriptor, params, top_k, capacity)


def _ladder(k: int, floor: int) -> list[int]:
    caps, c = [], floor
    while c < k:
        caps.append(c)
        c *= 2
    return caps + [k]


@eqx.filter_jit
def search_one(
    db: KeyframeDB,
    index: ZoneIndex,
    anchors: Anchors,
    range_m: Float[Array, " A"],
    descriptor: Float[Array, " F"],
    params: GateParams,
    top_k: int = 5,
    min_capacity: int = 64,
) -> Candidates:
    """One-shot gated search of a single query in one jitted call (no host round trip).

    The capacity is chosen on the device: `lax.switch` over the ladder min_capacity, 2 min_capacity,
    ..., K runs only the branch whose capacity covers the pivot zone, so the work follows the zone
    size. Exact; equals `rank_masked`. (Under `vmap` a switch runs every branch: use `search`.)

    Args:
        db, index, anchors: database, its zone index, the anchors (A).
        range_m: (A,) ranges [m], NaN = not heard. descriptor: (F,) query descriptor.
        params: zone widths. top_k, min_capacity: static ints (top_k <= K).

    Returns:
        `Candidates` of the query.
    """
    k = index.order.shape[1]
    caps = _ladder(k, max(_pow2(top_k), _pow2(min_capacity)))
    need = zone_counts(index, anchors, range_m, params)
    branch = jnp.searchsorted(jnp.asarray(caps), need, side="left")
    fns = [functools.partial(_branch, db, index, anchors, params, top_k, c) for c in caps]
    return jax.lax.switch(jnp.minimum(branch, len(caps) - 1), fns, range_m, descriptor)


@eqx.filter_jit
def search_one_full(db: KeyframeDB, descriptor: Float[Array, " F"], top_k: int = 5) -> Candidates:
    """One-shot ungated search of a single (F,) query descriptor in one jitted call."""
    return rank_full(db, descriptor, top_k)


def _pow2(n: int) -> int:
    return 1 << max(0, int(n - 1).bit_length())


def _check_batch(db: KeyframeDB, anchors: Anchors, descriptors, ranges, top_k: int) -> None:
    if descriptors.ndim != 2 or descriptors.shape[1] != db.descriptor.shape[1]:
        raise InputError(
            f"query descriptors: expected shape (Q, {db.descriptor.shape[1]}), got {tuple(descriptors.shape)}"
        )
    if ranges is not None and (ranges.ndim != 2 or ranges.shape != (descriptors.shape[0], anchors.position.shape[0])):
        raise InputError(
            f"query ranges: expected shape ({descriptors.shape[0]}, {anchors.position.shape[0]}), "
            f"got {tuple(ranges.shape)}"
        )
    if not 1 <= top_k <= db.n_keyframes:
        raise InputError(f"top_k must be in [1, {db.n_keyframes}], got {top_k}")


def search_full(db: KeyframeDB, descriptors, top_k: int = 5) -> Candidates:
    """Ungated batched search: `rank_full` vmapped over (Q, F) query descriptors."""
    descriptors = jnp.asarray(descriptors)
    if descriptors.ndim != 2 or descriptors.shape[1] != db.descriptor.shape[1]:
        raise InputError(
            f"query descriptors: expected shape (Q, {db.descriptor.shape[1]}), got {tuple(descriptors.shape)}"
        )
    if not 1 <= top_k <= db.n_keyframes:
        raise InputError(f"top_k must be in [1, {db.n_keyframes}], got {top_k}")
    return _full_batch(db, descriptors, top_k)


def search(
    db: KeyframeDB,
    index: ZoneIndex,
    anchors: Anchors,
    descriptors,
    ranges,
    params: GateParams | None = None,
    top_k: int = 5,
    batch: int = 32,
    min_capacity: int = 64,
) -> Candidates:
    """Gated batched search, exact and proportional in work to the zone sizes.

    Queries are grouped by the capacity their pivot zone needs (a power of two, at least `top_k`
    and `min_capacity`, at most K: a query with no usable range lands in the K group, i.e. the full
    search); each group
    runs as jitted `vmap`s of `rank_indexed` over chunks of `batch` queries (the last chunk padded),
    so compilations stay few: one per capacity, at most log2(K / min_capacity) + 1.

    Args:
        db, index, anchors: database, its zone index for `anchors`, the anchors (A).
        descriptors: (Q, F) query descriptors. ranges: (Q, A) ranges [m], NaN = not heard.
        params: zone widths (defaults when None). top_k: candidates per query.
        batch: queries per jitted call (static).
        min_capacity: smallest capacity (fewer compilations; gathering a few dozen rows is cheap).

    Returns:
        `Candidates` with a leading Q axis.
    """
    params = GateParams() if params is None else params
    descriptors = np.asarray(descriptors)
    ranges = np.asarray(ranges, dtype=np.asarray(anchors.position).dtype)
    _check_batch(db, anchors, descriptors, ranges, top_k)
    q = descriptors.shape[0]
    k = db.n_keyframes
    counts = np.asarray(_counts_batch(index, anchors, ranges, params))
    floor = max(_pow2(top_k), _pow2(min_capacity))
    caps = np.array([min(k, max(floor, _pow2(int(c)))) for c in counts])
    out_index = np.full((q, top_k), -1, np.int32)
    out_dist = np.full((q, top_k), np.inf, np.asarray(db.descriptor).dtype)
    out_n = np.zeros(q, np.int32)
    if batch < 1:
        raise InputError(f"batch must be >= 1, got {batch}")
    pending = []  # dispatch every chunk before reading any back (JAX runs them asynchronously)
    for cap in np.unique(caps):
        sel = np.nonzero(caps == cap)[0]
        for start in range(0, sel.size, batch):
            part = sel[start : start + batch]
            padded = np.concatenate([part, np.full(batch - part.size, part[0])])
            res = _indexed_batch(db, index, anchors, ranges[padded], descriptors[padded], params, top_k, int(cap))
            pending.append((part, res))
    for part, res in pending:
        n = part.size
        out_index[part] = np.asarray(res.index)[:n]
        out_dist[part] = np.asarray(res.distance)[:n]
        out_n[part] = np.asarray(res.n_admissible)[:n]
    return Candidates(
        index=jnp.asarray(out_index),
        distance=jnp.asarray(out_dist),
        n_admissible=jnp.asarray(out_n),
    )
