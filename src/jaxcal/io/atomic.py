"""Atomic file writes: a temporary file in the target's folder, then `os.replace`.

Every file jaxcal writes goes through `atomic_path`, so that

* a reader (or a crash, Ctrl-C, SIGTERM) sees either the old file or the complete new one, never a
  torn one: the temporary file is renamed into place only after it was written, closed and fsynced;
* the file gets the permissions the umask gives, `0o666 & ~umask` (0644 under umask 022;
  `tempfile.mkstemp` alone makes 0600, which nobody else could read), also when it replaces a file;
* no temporary file outlives the process: live temporaries are registered, and
  `discard_temporaries()` (called by the command line's signal handler before it exits) removes them.
  The rename and the removal share one lock, so an interrupt either lands before the rename (the old
  file stays, the temporary goes) or after it (the new file is complete).

    with atomic_path("out.h5") as tmp:
        with h5py.File(tmp, "w") as f:
            ...
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

__all__ = [
    "atomic_path",
    "atomic_write_text",
    "atomic_write_bytes",
    "discard_temporaries",
    "umask",
    "REPLACE_LOCK",
]

# Held while a temporary file is renamed into place, and by `discard_temporaries`.
REPLACE_LOCK = threading.Lock()
_LIVE: set[str] = set()


def umask() -> int:
    """The process umask, read without changing it where the system allows (Linux /proc)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)  # elsewhere: the classic read-by-setting (not thread-safe, brief)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, fsync: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success it replaces `path`, on any exception it is removed.

    Args:
        path: the file to (over)write. Its folder must exist (see `commands._common.check_output_path`
            for the user-facing checks done before any work).
        fsync: flush the temporary file to disk before the rename (crash safety on power loss).
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    os.close(fd)
    _LIVE.add(tmp)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~umask())
        if fsync:
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        with REPLACE_LOCK:
            os.replace(tmp, path)
            _LIVE.discard(tmp)
    finally:
        if tmp in _LIVE:
            with REPLACE_LOCK:
                _LIVE.discard(tmp)
                with contextlib.suppress(OSError):
                    os.unlink(tmp)


def atomic_write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Write `text` to `path` atomically (see `atomic_path`); returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding=encoding)
    return Path(path)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write `data` to `path` atomically (see `atomic_path`); returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def discard_temporaries(timeout: float = 2.0) -> None:
    """Remove every live temporary file (for a signal handler about to exit the process).

    Waits up to `timeout` seconds for a rename in progress, then keeps the lock so that no rename
    starts afterwards (the process is about to end).
    """
    REPLACE_LOCK.acquire(timeout=timeout)
    for tmp in list(_LIVE):
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        _LIVE.discard(tmp)
