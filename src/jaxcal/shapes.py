"""Padded array lengths, so that inputs of similar size share one compiled program.

A jitted function compiles once per input shape. A loop over campaigns whose per-anchor range counts
differ by a few percent (a sweep, a family of simulated scenarios, a batch of recordings) would compile
every fit again, which costs more than the fit itself. Padding (with a mask) to the next length on a
coarse ladder lets such campaigns share shapes, for at most 25 % more work on the padding.
"""

from __future__ import annotations

import contextlib

__all__ = ["exact_lengths", "padded_length"]

_EXACT = False


def padded_length(n: int) -> int:
    """The smallest length >= n of the form m x 2^e with m in 4..7 (at most 25 % padding; 1..4 kept): the
    lengths that per-anchor range arrays (`jaxcal.trajectory.poses.group_by_anchor`, the clock offset's fit), the
    EM's thinned ranges and the route cells of the trajectory fits are padded to. n itself inside `exact_lengths`."""
    n = int(n)
    if n <= 4 or _EXACT:
        return max(n, 1)
    e = (n - 1).bit_length() - 3  # 2^(e+2) < n <= 2^(e+3)
    return -(-n // (1 << e)) * (1 << e)


@contextlib.contextmanager
def exact_lengths():
    """Within it, `padded_length(n)` is n: no padding (the reference the tests and benchmarks/sweep_shapes.py
    compare the padded fits with). Not thread-safe."""
    global _EXACT
    before, _EXACT = _EXACT, True
    try:
        yield
    finally:
        _EXACT = before
