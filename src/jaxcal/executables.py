"""Keep a long-running process below the kernel's limit on memory maps.

Every live XLA:CPU executable holds about three anonymous memory maps (code, constants, data), and
JAX's jit caches keep every executable they compiled alive. A process that compiles thousands of
programs (a sweep over many scenario shapes, a benchmark over families, a test suite) reaches the
kernel's `vm.max_map_count` (65,530 by default on Linux); the next compile cannot map its code and
XLA dies with a segmentation fault. `release_if_crowded` drops JAX's caches (the executables and
their maps go with them; later calls recompile) once the process holds more than `limit` maps.
"""

from __future__ import annotations

import gc

import jax

__all__ = ["MAPS_LIMIT", "map_count", "release_if_crowded"]

MAPS_LIMIT = 20_000  # a third of Linux's default vm.max_map_count: room for one large group of compiles


def map_count() -> int:
    """Number of memory maps of this process (0 where there is no /proc, e.g. macOS)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return 0


def release_if_crowded(limit: int = MAPS_LIMIT) -> bool:
    """Drop JAX's compilation caches when the process holds more than `limit` memory maps.

    Returns whether it did. Results are unchanged: later calls compile their programs again.
    """
    if map_count() <= limit:
        return False
    jax.clear_caches()
    gc.collect()
    return True
