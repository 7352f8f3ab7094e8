"""Helpers shared by the subcommands (light imports only)."""

from __future__ import annotations

import errno
import json
import math
import os
import sys
import tempfile
from pathlib import Path
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


# ------------------------------------------------------------------ output paths, checked before any work

_REASONS = {
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied (folder not writable)",
    errno.EPERM: "permission denied (folder not writable)",
    errno.ENOSPC: "no space left on the device",
    errno.EDQUOT: "disk quota exceeded",
    errno.ENOENT: "the folder does not accept new files",
    errno.ENOTDIR: "not a folder",
}


def _probe_folder(user_path: str, folder: Path) -> None:
    """Create and remove a file in `folder`: the true reason when files cannot be created there."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".jaxcal-probe.", dir=folder)
    except OSError as e:
        reason = _REASONS.get(e.errno, e.strerror or type(e).__name__)
        raise JaxcalError(f"{user_path}: cannot write in {folder}: {reason}") from None
    os.close(fd)
    os.unlink(probe)


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _input_paths(inputs) -> list[str]:
    out = []
    for p in inputs or ():
        if p is None:
            continue
        if isinstance(p, (list, tuple)):
            out += _input_paths(p)
        else:
            out.append(str(p))
    return out


class OutputPath:
    """An output path that passed `check_output_path`: `.path`, and `.existed` (it will be replaced)."""

    def __init__(self, path: Path, existed: bool):
        self.path = path
        self.existed = existed

    def __fspath__(self) -> str:
        return str(self.path)

    def __str__(self) -> str:
        return str(self.path)

    def note(self) -> str:
        """' (overwrote X)' for a summary line when the file existed before, else ''."""
        return f" (overwrote {self.path})" if self.existed else ""


def check_output_path(path, inputs=(), *, folder: bool = False) -> OutputPath:
    """Check an output path before any work; raise a one-line `JaxcalError` naming `path` and the reason.

    Args:
        path: the user's output file (or folder with `folder=True`, created with its parents).
        inputs: input paths of the same run (files or folders; nested lists allowed). An output that is
            one of them (same file, also through a symlink, hard link or `./`) is refused.
        folder: the output is a folder (demo, report): it may exist (as a folder) or be created.
    Returns:
        an `OutputPath`; `.existed` tells that an existing file will be replaced (say so in the summary).
    """
    text = str(path)
    if not text.strip():
        raise JaxcalError("output path is empty")
    p = Path(text)
    for inp in _input_paths(inputs):
        ip = Path(inp)
        if ip.is_file() and (_same_file(p, ip) or os.path.realpath(p) == os.path.realpath(ip)):
            what = "" if str(ip) == text else f" ({ip})"
            raise JaxcalError(f"{text}: is an input of this run{what}; choose another output file")
    if folder:
        if p.exists() and not p.is_dir():
            raise JaxcalError(f"{text}: exists and is not a folder")
        base = p
        while not base.exists():  # created with its parents: check the nearest existing ancestor
            if base.parent == base:
                break
            base = base.parent
        if not base.is_dir():
            raise JaxcalError(f"{text}: {base} is not a folder")
        _probe_folder(text, base if base != p else p)
        return OutputPath(p, False)
    if p.is_dir():
        raise JaxcalError(f"{text}: is a folder (give a file name, e.g. {p / 'out.h5'})")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.exists():
        raise JaxcalError(f"{text}: folder {parent} does not exist")
    if not parent.is_dir():
        raise JaxcalError(f"{text}: {parent} is not a folder")
    if p.exists() and not p.is_file():
        raise JaxcalError(f"{text}: exists and is not a regular file")
    _probe_folder(text, parent)
    return OutputPath(p, p.exists())


def check_inputs(*paths) -> None:
    """Every input file exists and is a file (a one-line error naming the first one that is not)."""
    for inp in _input_paths(paths):
        ip = Path(inp)
        if not ip.exists():
            raise JaxcalError(f"{inp}: no such file")
        if ip.is_dir():
            raise JaxcalError(f"{inp}: is a folder, expected a file")


def add_output_flags(p, json_help: str = "print one JSON object instead of text") -> None:
    """The `--json` and `--quiet` flags that every command printing a summary takes."""
    p.add_argument("--json", action="store_true", help=json_help)
    p.add_argument("--quiet", action="store_true", help="print nothing on success (errors still go to stderr)")


def say(args, text: str) -> None:
    """Print a summary line unless --quiet or --json."""
    if not getattr(args, "quiet", False) and not getattr(args, "json", False):
        print(text, flush=True)


def emit_json(args, obj: dict) -> None:
    """Print the JSON summary when --json (even with --quiet: asked for explicitly)."""
    if getattr(args, "json", False):
        print_json(obj)
