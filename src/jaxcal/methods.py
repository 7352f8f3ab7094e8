"""Registry of calibration methods, so that `jaxcal calibrate --method NAME` and the API dispatch alike.

Each entry maps a method name to `"module:function"`, imported only when used. A method function has
the signature `fn(dataset, params: Mapping[str, Any] | None = None, config: str | None = None) -> Result`:
`params` are overrides of the method's documented defaults (strings from `--set` are cast), `config`
names a mesh frame configuration (ignored by trajectory methods); `auto` (when the dataset has no
configuration of that name) is the triple `jaxcal.mesh.frame_choice.choose_frame` picks.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import Any

from jaxcal.errors import JaxcalError

MESH_METHODS: dict[str, str] = {
    "cf": "jaxcal.mesh.closed_form:calibrate",
    "pgp": "jaxcal.mesh.pgp:calibrate",
    "parametric": "jaxcal.mesh.parametric:calibrate",
    "batch": "jaxcal.mesh.batch:calibrate",
    "pgp+batch": "jaxcal.mesh.hybrid:calibrate",
}

TRAJECTORY_METHODS: dict[str, str] = {
    "gp": "jaxcal.trajectory.gp:calibrate",
    "nls": "jaxcal.trajectory.nls:calibrate",
    "ls": "jaxcal.trajectory.ls:calibrate",
}

# method -> "module:Class" of its parameter defaults (for `--list-params`); pgp+batch takes both
# (a key of both goes to both stages; `pgp.KEY` / `batch.KEY` picks one).
METHOD_PARAMS: dict[str, tuple[str, ...]] = {
    "cf": ("jaxcal.mesh.closed_form:ClosedFormParams",),
    "pgp": ("jaxcal.mesh.pgp:PGPParams",),
    "parametric": ("jaxcal.mesh.pgp:PGPParams",),
    "batch": ("jaxcal.mesh.batch:BatchParams",),
    "pgp+batch": ("jaxcal.mesh.pgp:PGPParams", "jaxcal.mesh.batch:BatchParams"),
    "gp": ("jaxcal.trajectory.gp:GPParams",),
    "nls": ("jaxcal.trajectory.nls:NLSParams",),
    "ls": ("jaxcal.trajectory.ls:LSParams",),
}

__all__ = ["MESH_METHODS", "TRAJECTORY_METHODS", "METHOD_PARAMS", "get_method", "calibrate", "param_defaults"]


def param_defaults(name: str) -> list:
    """Default parameter objects of method `name` (one per stage; see `METHOD_PARAMS`)."""
    if name not in METHOD_PARAMS:
        known = ", ".join(sorted(METHOD_PARAMS))
        raise JaxcalError(f"unknown method {name!r} (known: {known})")
    out = []
    for ref in METHOD_PARAMS[name]:
        module, _, cls = ref.partition(":")
        out.append(getattr(importlib.import_module(module), cls)())
    return out


def get_method(kind: str, name: str):
    """The calibration function registered as `name` for datasets of `kind` ('mesh' or 'trajectory')."""
    table = MESH_METHODS if kind == "mesh" else TRAJECTORY_METHODS
    if name not in table:
        known = ", ".join(sorted(table)) or "none yet"
        raise JaxcalError(f"unknown method {name!r} for {kind} data (known: {known})")
    module, _, func = table[name].partition(":")
    return getattr(importlib.import_module(module), func)


# methods whose function takes `progress` (called with the epochs done since its last call)
WITH_PROGRESS = frozenset({"pgp", "parametric"})


def calibrate(
    dataset,
    method: str,
    params: Mapping[str, Any] | None = None,
    config: str | None = None,
    progress=None,
):
    """Calibrate `dataset` (MeshDataset or TrajectoryDataset) with a registered method -> Result.

    `progress`: optional callback for the methods in `WITH_PROGRESS` (others ignore it), called with
    the epochs done since its last call. Runs with one BLAS thread (`jaxcal.blas_threads`): the fits
    factor small dense matrices thousands of times, where OpenBLAS's worker threads cost more than they
    give (the command line also sets OPENBLAS_NUM_THREADS=1 unless the user has set it).

    A loop over many datasets of different shapes compiles new programs on every call, and each live
    executable holds memory maps: first, JAX's caches are dropped when the process holds more than
    `jaxcal.executables.MAPS_LIMIT` maps (`release_if_crowded`), so such a loop never reaches the
    kernel's limit (a 20-campaign gp loop died at the 19th without this)."""
    from jaxcal.blas_threads import one_blas_thread
    from jaxcal.executables import release_if_crowded

    release_if_crowded()
    return one_blas_thread(_calibrate)(dataset, method, params, config, progress)


def _calibrate(dataset, method: str, params, config, progress):
    from jaxcal.data import MeshDataset

    kind = "mesh" if isinstance(dataset, MeshDataset) else "trajectory"
    fn = get_method(kind, method)
    if kind == "mesh" and config == "auto":  # the best-connected, best-conditioned triple
        from jaxcal.mesh.frame_choice import with_auto_config

        dataset, _ = with_auto_config(dataset)
    if progress is not None and kind == "mesh" and method in WITH_PROGRESS:
        return fn(dataset, params=params, config=config, progress=progress)
    return fn(dataset, params=params, config=config)
