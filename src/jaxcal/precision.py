"""Numerical precision of the calibration entry points."""

from __future__ import annotations

import functools

import jax

__all__ = ["in_float64"]


def in_float64(fn):
    """Run a calibration entry point with 64-bit JAX arrays (scoped, not the global config).

    Normal equations, GP Cholesky factors and the Hamiltonian Monte Carlo of `batch` need it (in float32
    the sampler's energy differences round away and it silently stays at its start); results are float64
    in the file anyway.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with jax.enable_x64(True):
            return fn(*args, **kwargs)

    return wrapper
