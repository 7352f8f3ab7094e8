"""Helpers shared by the subcommands (light imports only)."""

from __future__ import annotations

import json
import math
import sys
from typing import Any

from jaxcal.errors import JaxcalError


def load(path: str, kinds: tuple[str, ...] = ("mesh", "trajectory", "result")):
    """Read a contract file and check that its format is one of `kinds`."""
    from jaxcal.io import hdf5

    fmt = hdf5.read_format(path)
    if fmt not in kinds:
        raise JaxcalError(f"{path}: is a {fmt} file, expected {' or '.join(kinds)}")
    return hdf5.read(path)


def kind_of(obj) -> str:
    from jaxcal.data import MeshDataset, Result, TrajectoryDataset

    if isinstance(obj, MeshDataset):
        return "mesh"
    if isinstance(obj, TrajectoryDataset):
        return "trajectory"
    if isinstance(obj, Result):
        return "result"
    raise TypeError(type(obj).__name__)


def _clean(x: Any) -> Any:
    """JSON-safe: NaN/inf -> None, NumPy scalars and arrays -> Python."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if hasattr(x, "tolist"):
        return _clean(x.tolist())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def print_json(obj: dict) -> None:
    """Exactly one JSON object on stdout."""
    sys.stdout.write(json.dumps(_clean(obj), allow_nan=False) + "\n")
    sys.stdout.flush()
