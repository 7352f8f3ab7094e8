"""One BLAS/LAPACK thread for the small dense factorisations of the calibration entry points.

JAX's CPU Cholesky and triangular solves call SciPy's OpenBLAS, which starts one thread per core and
spins while it waits. For the small matrices here (a 300 x 300 GP Gram matrix) that costs far more
than it gives, and on a shared machine it is catastrophic: measured on the 2-core VM at load ~15, a
300 x 300 Cholesky took 113 ms of CPU with OpenBLAS's 2 threads and 0.84 ms with one
(benchmarks/gp_speed.py has the whole-run figures). `threadpoolctl` (well kept, pure Python) limits
the already-loaded BLAS libraries at run time, so no environment variable has to be set before NumPy
is imported; the limit is scoped and restored on return.
"""

from __future__ import annotations

import functools

import scipy.linalg  # noqa: F401  (loads SciPy's OpenBLAS, which JAX's CPU LAPACK calls, so the limit reaches it)
from threadpoolctl import threadpool_limits

__all__ = ["one_blas_thread"]


def one_blas_thread(fn):
    """Run `fn` with every loaded BLAS library limited to one thread (restored afterwards)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper
