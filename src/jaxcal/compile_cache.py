"""JAX's persistent compilation cache for the command line: compile a program once per machine.

Every `jaxcal` process compiles its XLA programs afresh; on a 2-core CPU that is most of a short
run (`calibrate` on the 12-node torgau recording: 32 s cold, 15 s with the cache) and minutes of a
`tune` (the gradient of the filter). `enable` points JAX's own persistent cache
(`jax_compilation_cache_dir`) at a directory, so a later process with the same programs (same
shapes, options and JAX version) loads them instead. Results are the same executables, so the same
numbers.

The command line calls `enable()` before any work. `JAXCAL_CACHE_DIR` chooses the directory
(default `$XDG_CACHE_HOME/jaxcal/xla`, else `~/.cache/jaxcal/xla`); `JAXCAL_CACHE_DIR=off` (or
empty, `0`, `none`) turns it off. An unwritable directory turns it off too, silently: the cache
only ever saves time. Only programs that took at least `min_compile_s` to compile are stored. The
cache has no size limit (JAX's limit needs the `filelock` package, not a dependency); the directory
can be deleted at any time.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

__all__ = ["ENV", "default_dir", "enable"]

ENV = "JAXCAL_CACHE_DIR"
_OFF = ("", "0", "off", "none", "false")


def default_dir() -> Path:
    """`$XDG_CACHE_HOME/jaxcal/xla`, else `~/.cache/jaxcal/xla`."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jaxcal" / "xla"


def enable(
    path: str | os.PathLike | None = None,
    min_compile_s: float = 1.0,
) -> Path | None:
    """Turn JAX's persistent compilation cache on for this process.

    Args:
        path: the directory (None: `JAXCAL_CACHE_DIR`, else `default_dir()`).
        min_compile_s: store only programs whose compilation took at least this long [s].

    Returns:
        The directory in use, or None when the cache is off (`JAXCAL_CACHE_DIR=off`, or the
        directory cannot be created or written).
    """
    if path is None:
        env = os.environ.get(ENV)
        if env is not None and env.strip().lower() in _OFF:
            return None
        path = env or default_dir()
    where = Path(path).expanduser()
    try:
        where.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    if not os.access(where, os.W_OK | os.X_OK):
        return None
    jax.config.update("jax_compilation_cache_dir", str(where))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_s))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return where
