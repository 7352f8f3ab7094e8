"""Datasets and results: immutable pytrees of host arrays, validated on construction.

The field layout mirrors the HDF5 contract (`CONTRACT.md` section 1) one to one, so that reading and
writing a file is a plain copy. Units: metres, seconds, dBm. Missing values are NaN.

Array fields hold NumPy arrays with the contract's dtypes (converted on construction); ids, names and
other metadata are static fields. `jax.tree_util` sees only the arrays, so a dataset can be passed
through `jax.tree.map` or `eqx.filter_jit` as it is; constructing one runs the checks, while
flattening and unflattening (as JAX transforms do) does not.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, cast

import equinox as eqx
import numpy as np

from jaxcal.errors import DataError

__all__ = ["MeshDataset", "TrajectoryDataset", "Result", "mesh_true_distances"]


def _as(dtype):
    def convert(x):
        return None if x is None else np.asarray(x, dtype=dtype)

    return convert


def _as_ids(x) -> tuple[str, ...]:
    return tuple(str(v) for v in x)


def _shape_str(shape) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ")"


def _check_shape(owner: str, field: str, arr, shape: tuple, labels: str) -> None:
    """`shape` entries are ints or None (any size)."""
    if arr is None:
        return
    ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape, strict=False))
    if not ok:
        want = ", ".join(lab if s is None else f"{lab}={s}" for s, lab in zip(shape, labels.split(), strict=False))
        raise DataError(f"{owner}.{field}: expected shape ({want}), got {_shape_str(arr.shape)}")


def _check_unique(owner: str, field: str, ids: tuple[str, ...]) -> None:
    seen = set()
    for i in ids:
        if i in seen:
            raise DataError(f"{owner}.{field}: duplicate id {i!r}")
        seen.add(i)


def _check_nonneg(owner: str, field: str, arr) -> None:
    if arr is None:
        return
    bad = arr < 0  # NaN compares False: missing values pass
    if np.any(bad):
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise DataError(f"{owner}.{field}: negative value {arr[idx]!r} at index {idx}")


def _check_no_inf(owner: str, field: str, arr) -> None:
    if arr is not None and np.any(np.isinf(arr)):
        raise DataError(f"{owner}.{field}: contains infinite values (use NaN for missing)")


def _check_finite(owner: str, field: str, arr) -> None:
    if arr is not None and not np.all(np.isfinite(arr)):
        idx = tuple(int(i) for i in np.argwhere(~np.isfinite(arr))[0])
        raise DataError(f"{owner}.{field}: non-finite value at index {idx} (not allowed here)")


def _check_sorted(owner: str, field: str, t, strict: bool) -> None:
    if t is None or t.size < 2:
        return
    d = np.diff(t)
    bad = d <= 0 if strict else d < 0
    if np.any(bad):
        i = int(np.argmax(bad))
        word = "strictly increasing" if strict else "non-decreasing"
        raise DataError(f"{owner}.{field}: must be {word}; t[{i}]={t[i]!r} then t[{i + 1}]={t[i + 1]!r}")


def _check_index(owner: str, field: str, idx, n: int) -> None:
    if idx is None or idx.size == 0:
        return
    if idx.min() < 0 or idx.max() >= n:
        raise DataError(f"{owner}.{field}: index out of range [0, {n}) (min {idx.min()}, max {idx.max()})")


def _check_los(owner: str, field: str, los) -> None:
    if los is not None and los.size and not np.all(np.isin(los, (-1, 0, 1))):
        raise DataError(f"{owner}.{field}: values must be 1 (LOS), 0 (NLOS) or -1 (unknown)")


class MeshDataset(eqx.Module):
    """Nodes that range each other: a stream of inter-node distance matrices (CONTRACT 1.1).

    Attributes:
        name: dataset name.
        node_ids: (N,) unique node ids.
        time: (K,) epoch times [s], non-decreasing.
        range: (K, N, N) measured range i->j [m]; NaN = no measurement; diagonal NaN.
        truth: (N, D) true positions [m] (D = 2 or 3), NaN rows unknown; or None.
        los: (N, N) int8, 1 LOS, 0 NLOS, -1 unknown; or None.
        fp_rssi, rx_rssi: (K, N, N) signal powers [dBm]; or None.
        configs: name -> (a0, a1, a2) node indices defining a frame.
        description, source, license: optional metadata.
    """

    name: str = eqx.field(static=True)
    node_ids: tuple[str, ...] = eqx.field(static=True, converter=_as_ids)
    time: np.ndarray = eqx.field(converter=_as(np.float64))
    range: np.ndarray = eqx.field(converter=_as(np.float32))
    truth: np.ndarray | None = eqx.field(default=None, converter=_as(np.float64))
    los: np.ndarray | None = eqx.field(default=None, converter=_as(np.int8))
    fp_rssi: np.ndarray | None = eqx.field(default=None, converter=_as(np.float32))
    rx_rssi: np.ndarray | None = eqx.field(default=None, converter=_as(np.float32))
    configs: tuple[tuple[str, tuple[int, int, int]], ...] = eqx.field(
        default=(), static=True, converter=lambda c: _as_configs(c)
    )
    description: str | None = eqx.field(default=None, static=True)
    source: str | None = eqx.field(default=None, static=True)
    license: str | None = eqx.field(default=None, static=True)

    def __check_init__(self):
        o = "MeshDataset"
        n = len(self.node_ids)
        _check_unique(o, "node_ids", self.node_ids)
        if n < 3:
            raise DataError(f"{o}.node_ids: need at least 3 nodes to define a frame, got {n}")
        _check_shape(o, "time", self.time, (None,), "K")
        k = self.time.shape[0]
        _check_finite(o, "time", self.time)
        _check_sorted(o, "time", self.time, strict=False)
        _check_shape(o, "range", self.range, (k, n, n), "K N N")
        _check_no_inf(o, "range", self.range)
        _check_nonneg(o, "range", self.range)
        if self.truth is not None:
            _check_shape(o, "truth", self.truth, (n, None), "N D")
            if self.truth.shape[1] not in (2, 3):
                raise DataError(f"{o}.truth: D must be 2 or 3, got {self.truth.shape[1]}")
            _check_no_inf(o, "truth", self.truth)
        _check_shape(o, "los", self.los, (n, n), "N N")
        _check_los(o, "los", self.los)
        for f in ("fp_rssi", "rx_rssi"):
            _check_shape(o, f, getattr(self, f), (k, n, n), "K N N")
        for cname, idx in self.configs:
            if len(set(idx)) != 3 or min(idx) < 0 or max(idx) >= n:
                raise DataError(f"{o}.configs[{cname!r}]: need 3 distinct node indices in [0, {n}), got {idx}")

    @property
    def n_nodes(self) -> int:
        return len(self.node_ids)

    @property
    def n_epochs(self) -> int:
        return int(self.time.shape[0])

    def config(self, name: str | None) -> tuple[int, int, int]:
        """Node indices (a0, a1, a2) of a named configuration; (0, 1, 2) when `name` is None."""
        if name is None:
            return dict(self.configs).get("default", (0, 1, 2))
        table = dict(self.configs)
        if name not in table:
            known = ", ".join(table) or "none"
            raise DataError(f"MeshDataset.configs: unknown configuration {name!r} (known: {known})")
        return table[name]


def _as_configs(c) -> tuple[tuple[str, tuple[int, int, int]], ...]:
    if c is None:
        return ()
    items = c.items() if isinstance(c, Mapping) else c
    # the triple's length is checked with the rest of the dataset (__check_init__)
    return tuple((str(k), cast(tuple[int, int, int], tuple(int(i) for i in v))) for k, v in items)


class TrajectoryDataset(eqx.Module):
    """A platform with known poses ranging to fixed anchors (CONTRACT 1.2).

    Attributes:
        name: dataset name.
        anchor_ids: (A,) unique anchor ids. tag_ids: (T,) unique tag ids.
        anchor_truth: (A, 3) surveyed anchor positions [m], NaN unknown; or None.
        lever_arm: (T, 3) tag antenna in the body frame [m].
        pose_time: (P,) [s], strictly increasing. pose_position: (P, 3) [m].
        pose_orientation: (P, 4) unit quaternions (x, y, z, w); or None (identity).
        range_time: (R,) [s], non-decreasing, same clock as poses.
        range_anchor, range_tag: (R,) int32 indices. range: (R,) float32 [m].
        range_los: (R,) int8 or None. fp_rssi, rx_rssi: (R,) float32 [dBm] or None.
    """

    name: str = eqx.field(static=True)
    anchor_ids: tuple[str, ...] = eqx.field(static=True, converter=_as_ids)
    tag_ids: tuple[str, ...] = eqx.field(static=True, converter=_as_ids)
    lever_arm: np.ndarray = eqx.field(converter=_as(np.float64))
    pose_time: np.ndarray = eqx.field(converter=_as(np.float64))
    pose_position: np.ndarray = eqx.field(converter=_as(np.float64))
    range_time: np.ndarray = eqx.field(converter=_as(np.float64))
    range_anchor: np.ndarray = eqx.field(converter=_as(np.int32))
    range_tag: np.ndarray = eqx.field(converter=_as(np.int32))
    range: np.ndarray = eqx.field(converter=_as(np.float32))
    anchor_truth: np.ndarray | None = eqx.field(default=None, converter=_as(np.float64))
    pose_orientation: np.ndarray | None = eqx.field(default=None, converter=_as(np.float64))
    range_los: np.ndarray | None = eqx.field(default=None, converter=_as(np.int8))
    fp_rssi: np.ndarray | None = eqx.field(default=None, converter=_as(np.float32))
    rx_rssi: np.ndarray | None = eqx.field(default=None, converter=_as(np.float32))
    description: str | None = eqx.field(default=None, static=True)
    source: str | None = eqx.field(default=None, static=True)
    license: str | None = eqx.field(default=None, static=True)

    def __check_init__(self):
        o = "TrajectoryDataset"
        a, t = len(self.anchor_ids), len(self.tag_ids)
        _check_unique(o, "anchor_ids", self.anchor_ids)
        _check_unique(o, "tag_ids", self.tag_ids)
        if a < 1 or t < 1:
            raise DataError(f"{o}: need at least one anchor and one tag (got {a} anchors, {t} tags)")
        _check_shape(o, "anchor_truth", self.anchor_truth, (a, 3), "A 3")
        _check_no_inf(o, "anchor_truth", self.anchor_truth)
        _check_shape(o, "lever_arm", self.lever_arm, (t, 3), "T 3")
        _check_finite(o, "lever_arm", self.lever_arm)
        _check_shape(o, "pose_time", self.pose_time, (None,), "P")
        p = self.pose_time.shape[0]
        if p < 2:
            raise DataError(f"{o}.pose_time: need at least 2 poses, got {p}")
        _check_finite(o, "pose_time", self.pose_time)
        _check_sorted(o, "pose_time", self.pose_time, strict=True)
        _check_shape(o, "pose_position", self.pose_position, (p, 3), "P 3")
        _check_finite(o, "pose_position", self.pose_position)
        if self.pose_orientation is not None:
            _check_shape(o, "pose_orientation", self.pose_orientation, (p, 4), "P 4")
            _check_finite(o, "pose_orientation", self.pose_orientation)
            norms = np.linalg.norm(self.pose_orientation, axis=1)
            if np.any(np.abs(norms - 1.0) > 1e-3):
                i = int(np.argmax(np.abs(norms - 1.0)))
                raise DataError(f"{o}.pose_orientation: quaternion {i} is not unit (norm {norms[i]:.6g})")
        _check_shape(o, "range_time", self.range_time, (None,), "R")
        r = self.range_time.shape[0]
        _check_finite(o, "range_time", self.range_time)
        _check_sorted(o, "range_time", self.range_time, strict=False)
        for f in ("range_anchor", "range_tag", "range", "range_los", "fp_rssi", "rx_rssi"):
            _check_shape(o, f, getattr(self, f), (r,), "R")
        _check_index(o, "range_anchor", self.range_anchor, a)
        _check_index(o, "range_tag", self.range_tag, t)
        _check_no_inf(o, "range", self.range)
        _check_nonneg(o, "range", self.range)
        _check_los(o, "range_los", self.range_los)

    @property
    def n_anchors(self) -> int:
        return len(self.anchor_ids)

    @property
    def n_ranges(self) -> int:
        return int(self.range_time.shape[0])


class Result(eqx.Module):
    """What a calibration produced (CONTRACT 1.3).

    Attributes:
        ids: (N,) node or anchor ids, in the input's order.
        position: (N, D) final estimate [m]; NaN row = no estimate.
        method: method name. params: every parameter used (JSON-serialisable).
        dataset: the input dataset's name. frame: `anchors:i0,i1,i2` or `world`.
        covariance: (N, D, D) [m^2] or None.
        track_time: (K,) [s] or None. track_position: (K, N, D) [m] or None.
        software: producing software and version.
    """

    ids: tuple[str, ...] = eqx.field(static=True, converter=_as_ids)
    position: np.ndarray = eqx.field(converter=_as(np.float64))
    method: str = eqx.field(static=True)
    dataset: str = eqx.field(static=True)
    frame: str = eqx.field(static=True)
    params: Mapping[str, Any] = eqx.field(static=True, default_factory=dict)
    covariance: np.ndarray | None = eqx.field(default=None, converter=_as(np.float64))
    track_time: np.ndarray | None = eqx.field(default=None, converter=_as(np.float64))
    track_position: np.ndarray | None = eqx.field(default=None, converter=_as(np.float64))
    software: str = eqx.field(static=True, default="")
    name: str = eqx.field(static=True, default="")

    def __check_init__(self):
        o = "Result"
        n = len(self.ids)
        _check_unique(o, "ids", self.ids)
        _check_shape(o, "position", self.position, (n, None), "N D")
        d = self.position.shape[1]
        if d not in (2, 3):
            raise DataError(f"{o}.position: D must be 2 or 3, got {d}")
        _check_no_inf(o, "position", self.position)
        _check_shape(o, "covariance", self.covariance, (n, d, d), "N D D")
        if (self.track_time is None) != (self.track_position is None):
            raise DataError(f"{o}.track: track_time and track_position must both be given or both omitted")
        if self.track_time is not None:
            _check_shape(o, "track_time", self.track_time, (None,), "K")
            _check_sorted(o, "track_time", self.track_time, strict=False)
            _check_shape(o, "track_position", self.track_position, (self.track_time.shape[0], n, d), "K N D")
        if not (self.frame == "world" or self.frame.startswith("anchors:")):
            raise DataError(f"{o}.frame: must be 'world' or 'anchors:i0,i1,i2', got {self.frame!r}")

    def frame_anchors(self) -> tuple[int, int, int] | None:
        """The (a0, a1, a2) indices of a mesh frame, or None for `world`."""
        if self.frame == "world":
            return None
        a = tuple(int(s) for s in self.frame.split(":", 1)[1].split(","))
        if len(a) != 3:
            raise DataError(f"Result.frame: expected three indices, got {self.frame!r}")
        return a


def mesh_true_distances(truth: np.ndarray) -> np.ndarray:
    """(N, N) true distances [m] between nodes from (N, D) positions; NaN where a position is unknown."""
    diff = truth[:, None, :] - truth[None, :, :]
    return np.sqrt(np.sum(diff * diff, axis=-1))
