"""`jaxcal.blas_threads.one_blas_thread`: the limit holds inside, is restored after, and reaches the
OpenBLAS that JAX's CPU LAPACK calls."""

import jax.numpy as jnp
import numpy as np
from threadpoolctl import threadpool_info

from jaxcal.blas_threads import one_blas_thread


def _blas_threads():
    return {i["filepath"]: i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}


def test_one_blas_thread_inside_and_restored_after():
    before = _blas_threads()
    assert before  # SciPy's and NumPy's OpenBLAS are loaded by the import

    @one_blas_thread
    def factor(k):
        return jnp.linalg.cholesky(k), _blas_threads()

    k = np.eye(50) * 2.0 + 0.1
    chol, inside = factor(jnp.asarray(k))
    assert set(inside.values()) == {1}
    assert set(inside) >= set(before)
    np.testing.assert_allclose(np.asarray(chol), np.linalg.cholesky(k), rtol=1e-12)
    assert _blas_threads() == before
