"""jaxcal: UWB anchor self-calibration on a JAX array core.

Public API (imported lazily so that `import jaxcal` and `jaxcal --help` stay fast):

- Data: `MeshDataset`, `TrajectoryDataset`, `Result` (immutable pytrees, validated on construction).
- IO: `jaxcal.io.hdf5.read` / `write` (the HDF5 contract).
- Methods: `calibrate(dataset, method, ...)` dispatches to the registered methods (`jaxcal.methods`).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("jaxcal")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+local"

_LAZY = {
    "MeshDataset": "jaxcal.data",
    "TrajectoryDataset": "jaxcal.data",
    "Result": "jaxcal.data",
    "JaxcalError": "jaxcal.errors",
    "DataError": "jaxcal.errors",
    "FormatError": "jaxcal.errors",
    "calibrate": "jaxcal.methods",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'jaxcal' has no attribute {name!r}")
