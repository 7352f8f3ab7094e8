"""Reading and writing the HDF5 files of CONTRACT.md section 1.

`read(path)` returns a `MeshDataset`, `TrajectoryDataset` or `Result` according to the root attribute
`jaxcal_format`; `write(path, obj)` writes any of the three. Writing goes to a temporary file in the
same folder and is renamed into place, so a crash never leaves a half-written file under the target
name. Unknown groups and attributes are ignored on reading (the contract may be extended by optional
fields).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from jaxcal.data import MeshDataset, Result, TrajectoryDataset
from jaxcal.errors import DataError, FormatError
from jaxcal.io.atomic import atomic_path

__all__ = ["read", "write", "write_open", "read_format", "FORMAT_VERSION", "FORMATS"]

FORMAT_VERSION = 1
FORMATS = ("mesh", "trajectory", "result")
_STR = h5py.string_dtype("utf-8")


def _software() -> str:
    from jaxcal import __version__

    return f"jaxcal {__version__}"


def _attr_str(v: Any) -> str:
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.ndarray) and v.shape == ():
        return _attr_str(v[()])
    return str(v)


def _open(path: str | os.PathLike) -> h5py.File:
    p = Path(path)
    if not p.exists():
        raise FormatError(f"{p}: no such file")
    if p.is_dir():
        raise FormatError(f"{p}: is a folder, not an HDF5 file")
    try:
        return h5py.File(p, "r")
    except OSError as e:
        raise FormatError(f"{p}: not a readable HDF5 file ({str(e).splitlines()[0]})") from None


def _root_format(f: h5py.File, path) -> str:
    if "jaxcal_format" not in f.attrs:
        raise FormatError(f"{path}: missing root attribute 'jaxcal_format' (not a jaxcal file)")
    fmt = _attr_str(f.attrs["jaxcal_format"])
    if fmt not in FORMATS:
        raise FormatError(f"{path}: unknown jaxcal_format {fmt!r} (expected one of {', '.join(FORMATS)})")
    if "jaxcal_version" not in f.attrs:
        raise FormatError(f"{path}: missing root attribute 'jaxcal_version'")
    try:
        version = int(f.attrs["jaxcal_version"])
    except (TypeError, ValueError):
        raise FormatError(f"{path}: jaxcal_version must be an integer, got {f.attrs['jaxcal_version']!r}") from None
    if version > FORMAT_VERSION:
        raise FormatError(
            f"{path}: jaxcal_version {version} is newer than this jaxcal supports ({FORMAT_VERSION}); upgrade jaxcal"
        )
    if version < 1:
        raise FormatError(f"{path}: invalid jaxcal_version {version}")
    return fmt


def read_format(path: str | os.PathLike) -> str:
    """The `jaxcal_format` of a file ('mesh', 'trajectory' or 'result'), checked."""
    with _open(path) as f:
        return _root_format(f, path)


def _get(f: h5py.File, key: str, path, required: bool = True):
    if key not in f:
        if required:
            raise FormatError(f"{path}: missing dataset '{key}'")
        return None
    obj = f[key]
    if not isinstance(obj, h5py.Dataset):
        raise FormatError(f"{path}: '{key}' must be a dataset, found a group")
    if h5py.check_string_dtype(obj.dtype) is not None:
        return [s for s in obj.asstr()[()]] if obj.ndim else obj.asstr()[()]
    if obj.dtype.kind in "SO":
        return [s.decode("utf-8") if isinstance(s, bytes) else str(s) for s in obj[()]]
    return obj[()]


def _meta(f: h5py.File) -> dict[str, Any]:
    out = {}
    for k in ("description", "source", "license"):
        if k in f.attrs:
            out[k] = _attr_str(f.attrs[k])
    return out


def read(path: str | os.PathLike) -> MeshDataset | TrajectoryDataset | Result:
    """Read a contract file; raises `FormatError`/`DataError` with a one-line message on bad input."""
    with _open(path) as f:
        fmt = _root_format(f, path)
        name = _attr_str(f.attrs.get("name", Path(path).stem))
        try:
            if fmt == "mesh":
                return _read_mesh(f, path, name)
            if fmt == "trajectory":
                return _read_trajectory(f, path, name)
            return _read_result(f, path, name)
        except DataError as e:
            raise FormatError(f"{path}: {e}") from None
        except (KeyError, TypeError, ValueError, OSError) as e:
            raise FormatError(f"{path}: malformed {fmt} file ({type(e).__name__}: {e})") from None


def _read_mesh(f, path, name) -> MeshDataset:
    configs: dict[str, tuple[int, int, int]] = {}
    if "configs" in f:
        for k, v in f["configs"].items():
            arr = np.asarray(v[()])
            if arr.shape != (3,):
                raise FormatError(f"{path}: configs/{k} must have shape (3,), got {arr.shape}")
            configs[k] = (int(arr[0]), int(arr[1]), int(arr[2]))
    return MeshDataset(
        name=name,
        node_ids=_get(f, "nodes/id", path),
        time=_get(f, "epochs/time", path),
        range=_get(f, "epochs/range", path),
        truth=_get(f, "nodes/truth", path, False),
        los=_get(f, "links/los", path, False),
        fp_rssi=_get(f, "epochs/fp_rssi", path, False),
        rx_rssi=_get(f, "epochs/rx_rssi", path, False),
        configs=tuple(configs.items()),
        **_meta(f),
    )


def _read_trajectory(f, path, name) -> TrajectoryDataset:
    return TrajectoryDataset(
        name=name,
        anchor_ids=_get(f, "anchors/id", path),
        tag_ids=_get(f, "tags/id", path),
        anchor_truth=_get(f, "anchors/truth", path, False),
        lever_arm=_get(f, "tags/lever_arm", path),
        pose_time=_get(f, "poses/time", path),
        pose_position=_get(f, "poses/position", path),
        pose_orientation=_get(f, "poses/orientation", path, False),
        range_time=_get(f, "ranges/time", path),
        range_anchor=_get(f, "ranges/anchor", path),
        range_tag=_get(f, "ranges/tag", path),
        range=_get(f, "ranges/range", path),
        range_los=_get(f, "ranges/los", path, False),
        fp_rssi=_get(f, "ranges/fp_rssi", path, False),
        rx_rssi=_get(f, "ranges/rx_rssi", path, False),
        **_meta(f),
    )


def _read_result(f, path, name) -> Result:
    for k in ("method", "frame"):
        if k not in f.attrs:
            raise FormatError(f"{path}: result is missing root attribute '{k}'")
    params_raw = _attr_str(f.attrs.get("params", "{}"))
    try:
        params = json.loads(params_raw)
    except json.JSONDecodeError:
        raise FormatError(f"{path}: root attribute 'params' is not valid JSON") from None
    return Result(
        ids=_get(f, "ids", path),
        position=_get(f, "position", path),
        method=_attr_str(f.attrs["method"]),
        dataset=_attr_str(f.attrs.get("dataset", "")),
        frame=_attr_str(f.attrs["frame"]),
        params=params,
        covariance=_get(f, "covariance", path, False),
        track_time=_get(f, "track/time", path, False),
        track_position=_get(f, "track/position", path, False),
        software=_attr_str(f.attrs.get("software", "")),
        name=name,
    )


def _put(f: h5py.File, key: str, value, dtype=None) -> None:
    if value is None:
        return
    if dtype is _STR:
        f.create_dataset(key, data=np.array(list(value), dtype=object), dtype=_STR)
        return
    arr = np.asarray(value, dtype=dtype)
    kw = {"compression": "gzip", "compression_opts": 4, "shuffle": True} if arr.size > 4096 else {}
    f.create_dataset(key, data=arr, **kw)


def _write_root(f, fmt: str, name: str, obj) -> None:
    f.attrs["jaxcal_format"] = fmt
    f.attrs["jaxcal_version"] = np.int64(FORMAT_VERSION)
    f.attrs["name"] = name
    for k in ("description", "source", "license"):
        v = getattr(obj, k, None)
        if v:
            f.attrs[k] = v


def check_covariance(cov, ids) -> None:
    """Refuse a result covariance that is not a covariance: every finite (D, D) block must be symmetric
    positive semi-definite to float32 precision (a relative 1e-5 of its scale: the command line computes
    in float32, and `Result` stores every covariance as float64, so the precision it came from is not
    known here); NaN entries of a block are left out with their row and column (an unobservable
    coordinate). Raises FormatError naming the first bad id."""
    if cov is None:
        return
    tol = 1e-5
    c = np.asarray(cov, dtype=np.float64)
    for k in range(c.shape[0]):
        fin = np.isfinite(np.diag(c[k]))
        b = c[k][np.ix_(fin, fin)]
        if b.size == 0:
            continue
        scale = max(float(np.max(np.abs(b))), 1e-300)
        if (
            not np.isfinite(b).all()
            or np.max(np.abs(b - b.T)) > tol * scale
            or np.min(np.linalg.eigvalsh(0.5 * (b + b.T))) < -tol * scale
        ):
            name = ids[k] if k < len(ids) else str(k)
            raise FormatError(f"covariance of {name!r} is not symmetric positive semi-definite; refusing to write it")


def write(path: str | os.PathLike, obj: MeshDataset | TrajectoryDataset | Result) -> Path:
    """Write `obj` to `path` atomically (`jaxcal.io.atomic`: temporary file, then rename). Returns the path.

    A `Result` whose covariance is not symmetric positive semi-definite is refused (`check_covariance`)."""
    path = Path(path)
    if isinstance(obj, Result):
        check_covariance(obj.covariance, list(obj.ids))
    if path.parent and not path.parent.exists():
        raise FormatError(f"{path}: folder {path.parent} does not exist")
    if path.is_dir():
        raise FormatError(f"{path}: is a folder, not a file")
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        _write_obj(f, obj)
    return path


def write_open(f: h5py.File, obj: MeshDataset | TrajectoryDataset | Result) -> None:
    """Write `obj` into an HDF5 file open for writing (for files that add their own groups)."""
    _write_obj(f, obj)


def _write_obj(f: h5py.File, obj) -> None:
    if isinstance(obj, MeshDataset):
        _write_root(f, "mesh", obj.name, obj)
        _put(f, "nodes/id", obj.node_ids, _STR)
        _put(f, "nodes/truth", obj.truth, np.float64)
        _put(f, "epochs/time", obj.time, np.float64)
        _put(f, "epochs/range", obj.range, np.float32)
        _put(f, "epochs/fp_rssi", obj.fp_rssi, np.float32)
        _put(f, "epochs/rx_rssi", obj.rx_rssi, np.float32)
        _put(f, "links/los", obj.los, np.int8)
        for cname, idx in obj.configs:
            _put(f, f"configs/{cname}", np.asarray(idx, dtype=np.int64), np.int64)
    elif isinstance(obj, TrajectoryDataset):
        _write_root(f, "trajectory", obj.name, obj)
        _put(f, "anchors/id", obj.anchor_ids, _STR)
        _put(f, "anchors/truth", obj.anchor_truth, np.float64)
        _put(f, "tags/id", obj.tag_ids, _STR)
        _put(f, "tags/lever_arm", obj.lever_arm, np.float64)
        _put(f, "poses/time", obj.pose_time, np.float64)
        _put(f, "poses/position", obj.pose_position, np.float64)
        _put(f, "poses/orientation", obj.pose_orientation, np.float64)
        _put(f, "ranges/time", obj.range_time, np.float64)
        _put(f, "ranges/anchor", obj.range_anchor, np.int32)
        _put(f, "ranges/tag", obj.range_tag, np.int32)
        _put(f, "ranges/range", obj.range, np.float32)
        _put(f, "ranges/los", obj.range_los, np.int8)
        _put(f, "ranges/fp_rssi", obj.fp_rssi, np.float32)
        _put(f, "ranges/rx_rssi", obj.rx_rssi, np.float32)
    elif isinstance(obj, Result):
        _write_root(f, "result", obj.name or f"{obj.dataset}-{obj.method}", obj)
        f.attrs["method"] = obj.method
        f.attrs["params"] = json.dumps(_jsonable(dict(obj.params)), sort_keys=True)
        f.attrs["dataset"] = obj.dataset
        f.attrs["software"] = obj.software or _software()
        f.attrs["frame"] = obj.frame
        _put(f, "ids", obj.ids, _STR)
        _put(f, "position", obj.position, np.float64)
        _put(f, "covariance", obj.covariance, np.float64)
        _put(f, "track/time", obj.track_time, np.float64)
        _put(f, "track/position", obj.track_position, np.float64)
    else:
        raise TypeError(f"cannot write {type(obj).__name__} as a jaxcal file")


def _jsonable(x):
    """Parameters to plain JSON types (NumPy/JAX scalars and arrays included)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if hasattr(x, "tolist"):
        return x.tolist()
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    return str(x)
