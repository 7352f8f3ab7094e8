"""`pair_covariance`'s structured path (O(M^2 P), no M x M product) against the dense reference: the
(M, M) Sigma of `variance_components` and the sandwich g Sigma g^T (issue #26: thousands of pairs)."""

from __future__ import annotations

import numpy as np
import pytest

from jaxcal.mesh.pair_covariance import pair_covariance, variance_components


def _dense(jac, e, w, spread, i, j, n, prior, shared):
    """The covariance as `pair_covariance` computed it before: Sigma (M, M) formed, then g Sigma g^T
    through its eigen-decomposition (negative eigenvalues clipped)."""
    p = jac.shape[1]
    out = np.full((p, p), np.nan)
    lam, vec = np.linalg.eigh((jac.T * w) @ jac + np.diag(prior))
    null = lam <= 1e-10 * lam.max()
    keep = (vec[:, null] ** 2).sum(axis=1) < 1e-6
    jk, pk = jac[:, keep], prior[keep]
    sigma, parts = variance_components(jk, e, w, spread, i, j, n, pk, shared)
    g = np.linalg.inv((jk.T * w) @ jk + np.diag(pk)) @ (jk.T * w)
    lam, vec = np.linalg.eigh(0.5 * (sigma + sigma.T))
    root = g @ (vec * np.sqrt(np.maximum(lam, 0.0)))
    out[np.ix_(keep, keep)] = root @ root.T
    return out, parts


def _network(rng, n, share, with_offsets):
    """Jacobian of a random sparse 2-D network in the frame (0, 1, 2) (node 0 fixed, node 1 only x), with a
    common offset and per-node offsets (their priors) when `with_offsets`; errors, weights, spreads."""
    x = rng.uniform(0.0, 20.0, (n, 2))
    i, j = np.triu_indices(n, 1)
    keep = (rng.random(i.size) < share) | (j < 3)
    keep &= j != n - 1
    i, j = i[keep], j[keep]
    i, j = np.r_[i, 0], np.r_[j, n - 1]  # node n - 1 ranges node 0 only: its coordinates are not fixed
    u = (x[i] - x[j]) / np.linalg.norm(x[i] - x[j], axis=1)[:, None]
    full = np.zeros((i.size, 2 * n))
    rows = np.arange(i.size)
    for c in range(2):
        full[rows, 2 * i + c], full[rows, 2 * j + c] = u[:, c], -u[:, c]
    jac, prior = full[:, np.r_[2, np.arange(4, 2 * n)]], np.zeros(2 * n - 3)
    if with_offsets:
        node = np.zeros((i.size, n))
        node[rows, i] = node[rows, j] = 1.0
        jac = np.column_stack([jac, np.ones(i.size), node])
        prior = np.r_[prior, 0.01, np.full(n, 100.0)]
    e = rng.normal(0.0, 0.05, i.size) + 0.3 * (rng.random(i.size) < 0.3)
    return jac, e, rng.uniform(0.01, 1.0, i.size), rng.uniform(0.05, 0.4, i.size), i, j, prior


@pytest.mark.parametrize("n, share, with_offsets", [(9, 1.0, True), (16, 0.5, False), (30, 0.3, True)])
def test_structured_pair_covariance_equals_dense_reference(rng, n, share, with_offsets):
    jac, e, w, spread, i, j, prior = _network(rng, n, share, with_offsets)
    # without a fitted offset the estimator carries a common offset: a second shared pattern (ones)
    shared = None if with_offsets else np.column_stack([spread, np.ones(i.size)])
    cov, parts = pair_covariance(jac, e, w, spread, i, j, n, prior, shared)
    ref, ref_parts = _dense(jac, e, w, spread, i, j, n, prior, shared)
    assert np.array_equal(np.isfinite(cov), np.isfinite(ref)) and np.isnan(cov).any()  # node n - 1 unfixed
    ok = np.isfinite(ref)
    np.testing.assert_allclose(cov[ok], ref[ok], rtol=0, atol=1e-9 * np.abs(ref[ok]).max())
    for k in ("t_I", "t_D", "t_N"):
        assert parts[k] == pytest.approx(ref_parts[k], rel=1e-8, abs=1e-12 * max(ref_parts[k], 1e-3))
    np.testing.assert_allclose(parts["t_S"], ref_parts["t_S"], rtol=1e-8, atol=1e-14)
