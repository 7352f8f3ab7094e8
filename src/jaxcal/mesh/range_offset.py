"""The common range offset of a network, fitted from positions and per-pair median ranges.

UWB ranges carry a common offset (antenna delays, the LOS excess delay: +0.2 m in the simulator's
channel, -0.1 to -0.3 m on DWM1001 boards). A filter that takes the ranges as unbiased cannot place a
planar network so that every distance equals its range plus a constant; it spreads the offset into a
scale error that grows with the site's extent (issue #26: 0.53 m aligned RMSE at N = 100, 0.27 m with
the offset removed). `fit_offset` fits positions and one offset c jointly to the per-pair medians
(robust soft-L1 loss, sparse Jacobian: cost about the measured pairs), starting from the filter's
positions; only c is returned. `batch.py` fits the same offset with its own robust model (`bias`).
"""

from __future__ import annotations

import warnings

import numpy as np

__all__ = ["pair_medians", "fit_offset"]


def pair_medians(z: np.ndarray) -> np.ndarray:
    """(N, N) per-pair median over epochs of (K, N, N) ranges (NaN: never measured)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(np.asarray(z, dtype=np.float64), axis=0) if z.shape[0] else np.full(z.shape[1:], np.nan)


def fit_offset(position: np.ndarray, med: np.ndarray, f_scale: float, max_nfev: int = 50) -> tuple[float, int]:
    """(c [m], pairs used): the offset of `med = |x_i - x_j| + c` fitted jointly with the 2-D positions
    (started at `position`, NaN rows left out) under scipy's soft-L1 loss of scale `f_scale` [m].
    NaN with 0 pairs when fewer pairs than unknowns are measured between placed nodes."""
    from scipy.optimize import least_squares
    from scipy.sparse import csr_matrix

    x = np.asarray(position, dtype=np.float64)[:, :2]
    placed = np.isfinite(x).all(axis=1)
    x = x[placed]
    med = np.asarray(med, dtype=np.float64)[np.ix_(placed, placed)]
    n = x.shape[0]
    iu, ju = np.triu_indices(n, k=1)
    ok = np.isfinite(med[iu, ju])
    i, j, z = iu[ok], ju[ok], med[iu, ju][ok]
    m = z.size
    if m < 2 * n - 2 or m < 3:  # positions up to a rigid motion, plus c
        return float("nan"), 0
    cols = np.stack([2 * i, 2 * i + 1, 2 * j, 2 * j + 1, np.full(m, 2 * n)], axis=1).ravel()
    sparsity = csr_matrix((np.ones(5 * m), (np.repeat(np.arange(m), 5), cols)), shape=(m, 2 * n + 1))
    x0 = np.concatenate([x.ravel(), [0.0]])

    def resid(theta):
        p = theta[:-1].reshape(n, 2)
        return np.linalg.norm(p[i] - p[j], axis=1) + theta[-1] - z

    fit = least_squares(
        resid, x0, jac_sparsity=sparsity, loss="soft_l1", f_scale=f_scale, x_scale="jac", max_nfev=max_nfev
    )
    c = float(fit.x[-1])
    return (c, m) if np.isfinite(c) else (float("nan"), 0)
