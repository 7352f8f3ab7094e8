"""The files of `jaxcal gate` (range-zone gated place recognition): keyframe database, queries, candidates.

Every file is also a valid contract file (CONTRACT.md 1), extended by one group:

- DB.h5: any jaxcal file (the simulator writes the prior mapping run as a `trajectory` file, so that
  `jaxcal calibrate DB.h5 --method gp` calibrates the anchors from it) plus the group `places/`:
  `position` (K, D) float64 keyframe positions [m], `descriptor` (K, F) float (one descriptor per
  keyframe, any place-recognition method), attribute `metric` = `cosine` | `l2`.
- QUERIES.h5: any jaxcal file plus the group `queries/`: `descriptor` (Q, F); optional `id` (Q,) strings,
  `truth` (Q, D) float64 true positions [m] (NaN = unknown; enables the success rate), and the ranges,
  either explicitly as `range` (Q, A') float32 [m] (NaN = not heard) with `anchor_id` (A',) strings naming
  the columns, or, for a `trajectory` file, `time` (Q,) [s]: the contract ranges (`ranges/time`,
  `ranges/anchor`, `ranges/range`) within the window of a query time are assigned to it (median per
  anchor), anchors named by `anchors/id`.
- RESULT.h5 (the anchors): a contract `result` (e.g. from `jaxcal calibrate --method gp`).
- OUT.h5: a contract `result` (method `gate`, frame `world`): `ids` = query ids, `position` = best
  candidate per query (NaN = none), plus `candidates/index` (Q, k) int32 keyframe indices (-1 = none),
  `candidates/distance` (Q, k) descriptor distances, `candidates/n_admissible` (Q,) int32.
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from jaxcal.data import Result, TrajectoryDataset
from jaxcal.errors import FormatError, JaxcalError
from jaxcal.io import hdf5
from jaxcal.io.atomic import atomic_path

__all__ = ["read_db", "read_queries", "ranges_near", "write_candidates", "write_places_files"]


def _dataset(f: h5py.File, key: str, path, required: bool = True):
    """`hdf5._get` (missing / not a dataset: one-line `FormatError`), strings as a list of str."""
    value = hdf5._get(f, key, path, required)
    return [value] if isinstance(value, str) else value


def read_db(path: str | os.PathLike):
    """(positions (K, D), descriptors (K, F), metric) from the `places/` group of a jaxcal file."""
    hdf5.read_format(path)  # raises FormatError with one line for a non-jaxcal file
    with h5py.File(path, "r") as f:
        if "places" not in f:
            raise FormatError(f"{path}: no 'places' group (not a keyframe database)")
        pos = np.asarray(_dataset(f, "places/position", path), dtype=np.float64)
        desc = np.asarray(_dataset(f, "places/descriptor", path))
        metric = f["places"].attrs.get("metric", "cosine")
        metric = metric.decode() if isinstance(metric, bytes) else str(metric)
    if pos.ndim != 2 or pos.shape[1] not in (2, 3) or pos.shape[0] < 1:
        raise FormatError(f"{path}: places/position must have shape (K, 2|3), got {pos.shape}")
    if desc.ndim != 2 or desc.shape[0] != pos.shape[0] or desc.dtype.kind not in "fiu":
        raise FormatError(f"{path}: places/descriptor must be numeric of shape ({pos.shape[0]}, F), got {desc.shape}")
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(desc))):
        raise FormatError(f"{path}: places/position and places/descriptor must be finite")
    if metric not in ("cosine", "l2"):
        raise FormatError(f"{path}: places metric must be 'cosine' or 'l2', got {metric!r}")
    return pos, desc, metric


def read_queries(path: str | os.PathLike, window_s: float):
    """Query descriptors (Q, F), ranges (Q, A') [m], anchor ids, query ids, truth (Q, D) or None.

    Args:
        path: a jaxcal file with a `queries/` group. window_s: width [s] of the window around a query time
            whose ranges are assigned to it (`ranges_near`; with `queries/time` only).
    """
    fmt = hdf5.read_format(path)
    with h5py.File(path, "r") as f:
        if "queries" not in f:
            raise FormatError(f"{path}: no 'queries' group (not a query file)")
        desc = np.asarray(_dataset(f, "queries/descriptor", path))
        if desc.ndim != 2 or desc.shape[0] < 1 or desc.dtype.kind not in "fiu":
            raise FormatError(f"{path}: queries/descriptor must be numeric of shape (Q, F), got {desc.shape}")
        q = desc.shape[0]
        ids = _dataset(f, "queries/id", path, False) or [f"q{i}" for i in range(q)]
        truth = _dataset(f, "queries/truth", path, False)
        explicit = _dataset(f, "queries/range", path, False)
        qtime = _dataset(f, "queries/time", path, False)
        if explicit is not None:
            ranges = np.asarray(explicit, dtype=np.float64)
            anchor_ids = _dataset(f, "queries/anchor_id", path)
        elif qtime is not None and fmt == "trajectory":
            anchor_ids = _dataset(f, "anchors/id", path)
            ranges = ranges_near(
                np.asarray(qtime, np.float64),
                np.asarray(_dataset(f, "ranges/time", path), np.float64),
                np.asarray(_dataset(f, "ranges/anchor", path), np.int64),
                np.asarray(_dataset(f, "ranges/range", path), np.float64),
                len(anchor_ids),
                window_s,
            )
        else:
            raise FormatError(f"{path}: queries need 'queries/range' or 'queries/time' in a trajectory file")
    if len(ids) != q:
        raise FormatError(f"{path}: queries/id has {len(ids)} entries for {q} descriptors")
    if ranges.shape != (q, len(anchor_ids)):
        raise FormatError(f"{path}: query ranges must have shape ({q}, {len(anchor_ids)}), got {ranges.shape}")
    if np.any(ranges < 0) or np.any(np.isinf(ranges)):
        raise FormatError(f"{path}: query ranges must be non-negative (NaN = not heard)")
    if truth is not None:
        truth = np.asarray(truth, np.float64)
        if truth.ndim != 2 or truth.shape[0] != q:
            raise FormatError(f"{path}: queries/truth must have shape ({q}, D), got {truth.shape}")
    return desc, ranges, [str(a) for a in anchor_ids], [str(i) for i in ids], truth


def ranges_near(qtime, rtime, ranchor, rrange, n_anchors: int, window_s: float) -> np.ndarray:
    """(Q, A) median of the ranges [m] within window_s / 2 of each query time [s]; NaN where none.

    Args:
        qtime: (Q,) query times. rtime, ranchor, rrange: (M,) contract ranges (time-sorted), their anchor
            indices and values. n_anchors: A. window_s: window width [s], > 0.
    """
    if window_s <= 0:
        raise JaxcalError(f"--window must be positive, got {window_s}")
    if np.any(ranchor < 0) or np.any(ranchor >= n_anchors):
        raise JaxcalError("ranges/anchor: index out of range")
    out = np.full((qtime.size, n_anchors), np.nan)
    lo = np.searchsorted(rtime, qtime - window_s / 2, side="left")
    hi = np.searchsorted(rtime, qtime + window_s / 2, side="right")
    for i in range(qtime.size):
        a, r = ranchor[lo[i] : hi[i]], rrange[lo[i] : hi[i]]
        for j in np.unique(a):
            v = r[(a == j) & np.isfinite(r)]
            if v.size:
                out[i, j] = np.median(v)
    return out


def _write_with_group(path, obj, group: str, items: dict, attrs: dict | None = None) -> None:
    """A contract file of `obj` plus one extension group of datasets (lists become string datasets)."""
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        hdf5.write_open(f, obj)
        g = f.create_group(group)
        for k, v in items.items():
            if isinstance(v, list):
                g.create_dataset(k, data=np.array(v, dtype=object), dtype=h5py.string_dtype())
            else:
                g.create_dataset(k, data=v)
        for k, v in (attrs or {}).items():
            g.attrs[k] = v


def write_candidates(path: str | os.PathLike, query_ids, best, candidates, params: dict, dataset: str) -> None:
    """OUT.h5: a `gate` result (best candidate position per query) plus the `candidates/` group.

    Args:
        path: the output file (its folder must exist). query_ids: (Q,) ids. best: (Q, D) positions [m].
        candidates: `gating.Candidates` (index, distance, n_admissible). params: the Result params.
        dataset: the Result's dataset name (the query file's stem).
    """
    p = Path(path)
    if not p.parent.exists():
        raise JaxcalError(f"{p}: folder {p.parent} does not exist")
    res = Result(ids=query_ids, position=best, method="gate", dataset=dataset, frame="world", params=params)
    with atomic_path(p) as tmp, h5py.File(tmp, "w") as f:
        hdf5.write_open(f, res)
        g = f.create_group("candidates")
        g.create_dataset("index", data=np.asarray(candidates.index, np.int32))
        g.create_dataset("distance", data=np.asarray(candidates.distance, np.float64))
        g.create_dataset("n_admissible", data=np.asarray(candidates.n_admissible, np.int32))


def write_places_files(directory, scene, anchor_error_m: float, seed: int):
    """Write a simulated scene (`sim.places`) as DB, queries and anchors files into `directory`.

    Returns:
        (db path, queries path, anchors path) as strings.
    """
    from jaxcal.sim.places import perturb_anchors

    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise JaxcalError(f"{d}: exists and is not a folder")
    d.mkdir(parents=True, exist_ok=True)
    a = scene.anchor_truth.shape[0]
    anchor_ids = [f"A{i}" for i in range(a)]

    def trajectory(name, time, pos, rng_matrix, los=None):
        qi, ai = np.nonzero(np.isfinite(rng_matrix))
        return TrajectoryDataset(
            name=name,
            anchor_ids=anchor_ids,
            tag_ids=["T0"],
            lever_arm=np.zeros((1, 3)),
            pose_time=time,
            pose_position=pos,
            range_time=time[qi],
            range_anchor=ai,
            range_tag=np.zeros(qi.size),
            range=rng_matrix[qi, ai],
            anchor_truth=scene.anchor_truth,
            range_los=None if los is None else los[qi, ai].astype(np.int8),
            source="jaxcal.sim.places",
            description="simulated repetitive container yard",
        )

    db_path, q_path, an_path = d / "places_db.h5", d / "places_queries.h5", d / "places_anchors.h5"
    _write_with_group(
        db_path,
        trajectory("places-prior", scene.keyframe_time, scene.keyframe_position, scene.keyframe_range),
        "places",
        {"position": scene.keyframe_position, "descriptor": scene.keyframe_descriptor},
        {"metric": "cosine"},
    )
    q = scene.query_time.size
    _write_with_group(
        q_path,
        trajectory("places-queries", scene.query_time, scene.query_position, scene.query_range, scene.query_los),
        "queries",
        {
            "descriptor": scene.query_descriptor,
            "time": scene.query_time,
            "truth": scene.query_position,
            "id": [f"q{i}" for i in range(q)],
        },
    )
    pos, cov = perturb_anchors(np.random.default_rng(seed + 1), scene.anchor_truth, anchor_error_m)
    hdf5.write(
        an_path,
        Result(
            ids=tuple(anchor_ids),
            position=pos,
            covariance=cov,
            method="simulated",
            dataset="places-prior",
            frame="world",
            params={"anchor_error_m": anchor_error_m, "seed": seed},
        ),
    )
    return str(db_path), str(q_path), str(an_path)
