"""Helpers shared by the subcommands (light imports only)."""

from __future__ import annotations

import errno
import json
import os
import sys
import tempfile
from pathlib import Path

from jaxcal.errors import JaxcalError
from jaxcal.io.jsonsafe import json_safe


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


def print_json(obj: dict) -> None:
    """Exactly one JSON object on stdout."""
    sys.stdout.write(json.dumps(json_safe(obj), allow_nan=False) + "\n")
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
        reason = _REASONS.get(e.errno or 0, e.strerror or type(e).__name__)
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
        _probe_folder(text, base)
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


# ------------------------------------------------------------------ --config: a stored name or three node ids

CONFIG_HELP = (
    "mesh frame: a stored configuration's name (configs/NAME, e.g. conf1) or three node ids A0,A1,A2 "
    "(a0 at the origin, a1 on +x, a2 at y > 0); default: configs/default or the first three nodes"
)


def parse_config(text: str | None) -> str | tuple[str, str, str] | None:
    """`--config` as given: None, a configuration name, or three distinct node ids (comma-separated)."""
    if text is None:
        return None
    t = text.strip()
    if not t:
        raise JaxcalError("--config is empty (give a configuration name or three node ids A0,A1,A2)")
    if "," not in t:
        return t
    ids = tuple(s.strip() for s in t.split(","))
    if len(ids) != 3 or not all(ids) or len(set(ids)) != 3:
        raise JaxcalError(f"--config: expected a configuration name or three distinct node ids A0,A1,A2, got {text!r}")
    return ids


def resolve_config(ds, text: str | None):
    """(dataset, configuration name) for `--config TEXT` on a mesh dataset.

    A stored name is checked against `configs/`; three node ids (or, when they are not ids, three node
    indices) become a configuration of that name added to the returned dataset, so that every method,
    which takes a configuration name, accepts them.
    """
    import dataclasses

    cfg = parse_config(text)
    if cfg is None or not hasattr(ds, "node_ids"):
        return ds, None if cfg is None else text
    if isinstance(cfg, str):
        table = dict(ds.configs)
        if cfg not in table:
            known = ", ".join(table) or "none stored"
            raise JaxcalError(
                f"--config {cfg}: no such configuration in {ds.name} (known: {known}; or give three node ids A0,A1,A2)"
            )
        return ds, cfg
    ids = list(ds.node_ids)
    missing = [c for c in cfg if c not in ids]
    if not missing:
        idx = tuple(ids.index(c) for c in cfg)
    elif all(c.isdigit() for c in cfg) and all(int(c) < len(ids) for c in cfg):
        idx = tuple(int(c) for c in cfg)
    else:
        raise JaxcalError(
            f"--config {','.join(cfg)}: unknown node id(s) {', '.join(missing)} (nodes: {', '.join(ids)})"
        )
    name = ",".join(cfg)
    configs = {k: v for k, v in ds.configs}
    configs[name] = idx
    return dataclasses.replace(ds, configs=configs), name
