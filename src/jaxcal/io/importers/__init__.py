"""Importers of real UWB recordings into jaxcal datasets (`jaxcal import FORMAT SRC... -o OUT`).

One module per format; each exposes one function that takes the source paths and an optional `name`
and returns a validated `MeshDataset` or `TrajectoryDataset` (nothing is written here: the command
writes the result with `jaxcal.io.hdf5.write`). Policy shared by all importers:

- a missing file, a wrong header, an empty file or a file without a single usable row raises a
  one-line `JaxcalError` naming the file (and the line or column where it applies);
- a bad row in an otherwise good file (non-numeric cell, wrong field count, negative range) is
  skipped and counted, and the counts are reported in the dataset's `description`;
- `source` and `license` carry the dataset's origin and licence (from its SOURCE.txt / LICENSE).

`IMPORTERS` maps FORMAT -> (module, function, source argument names); `import_recording` dispatches.
"""

from __future__ import annotations

import importlib
import os

from jaxcal.errors import JaxcalError

__all__ = ["IMPORTERS", "import_recording"]

# FORMAT -> (module under jaxcal.io.importers, function, names of the source arguments in order)
IMPORTERS: dict[str, tuple[str, str, tuple[str, ...]]] = {
    "dwm1001-autocal": ("dwm1001", "import_dwm1001", ("SCENARIO_DIR", "NODES_CFG.yaml")),
    "hymn": ("hymn", "import_hymn", ("DATASET_ROOT",)),
    "cuhksz": ("cuhksz", "import_cuhksz", ("UWB.csv", "MOCAP.csv")),
    "hanyang": ("hanyang", "import_hanyang", ("RUN_DIR",)),
    "csv": ("csv", "import_csv", ("FILE",)),
}


def import_recording(fmt: str, *sources: str | os.PathLike, name: str | None = None, force: bool = False):
    """Convert a recording to a dataset.

    Args:
        fmt: one of `IMPORTERS` (e.g. "hymn").
        *sources: the format's source paths, in the order of `IMPORTERS[fmt][2]`.
        name: dataset name; default derived from the source path.
        force: for importers that join sources by id (dwm1001: range files and a layout yaml), import
            even when the ids do not match.

    Returns:
        A `MeshDataset` or `TrajectoryDataset`.
    """
    if fmt not in IMPORTERS:
        raise JaxcalError(f"unknown importer {fmt!r} (known: {', '.join(IMPORTERS)})")
    module, func, args = IMPORTERS[fmt]
    if len(sources) != len(args):
        raise JaxcalError(f"importer {fmt!r} takes {len(args)} source argument(s) {' '.join(args)}, got {len(sources)}")
    fn = getattr(importlib.import_module(f"jaxcal.io.importers.{module}"), func)
    import inspect

    if "force" in inspect.signature(fn).parameters:
        return fn(*sources, name=name, force=force)
    return fn(*sources, name=name)
