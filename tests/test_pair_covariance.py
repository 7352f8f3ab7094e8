"""`position_covariance` with a robust scale (what `--method pgp` reports): a gross-outlier pair neither
sizes the other pairs' errors nor widens every node, and an estimate off the pairs' fit is as uncertain
as its distance from it."""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from conftest import random_layout
from jaxcal.mesh.pair_covariance import polish, position_covariance


def network(rng, n=9, k=60, noise=0.05, outlier_m=4.0):
    pos, d = random_layout(rng, n, 20.0, min_sep=2.0)
    pos = pos - pos[0]
    c, s = pos[1] / np.linalg.norm(pos[1])
    rot = np.array([[c, s], [-s, c]])
    pos = pos @ rot.T  # frame (0, 1, 2): a0 at the origin, a1 on +x
    if pos[2, 1] < 0:
        pos[:, 1] *= -1
    r = d[None] + rng.normal(0, noise, (k, n, n))
    r = 0.5 * (r + np.swapaxes(r, 1, 2))
    r[:, 4, 7] += outlier_m  # one pair metres off at every epoch (an NLOS pair)
    r[:, 7, 4] += outlier_m
    r[:, np.arange(n), np.arange(n)] = np.nan
    return pos, r


def test_an_outlier_pair_does_not_widen_every_node(rng):
    pos, r = network(rng)
    est = pos + rng.normal(0, 0.03, pos.shape) * (np.arange(len(pos)) >= 2)[:, None]
    plain = position_covariance(r, est, (0, 1, 2))
    robust = position_covariance(r, est, (0, 1, 2), robust_scale=0.3)
    rms = lambda c: np.sqrt(np.trace(c, axis1=1, axis2=2))[2:]  # noqa: E731
    assert np.all(np.isfinite(robust[2:]))
    assert np.median(rms(robust)) < 0.25 < np.median(rms(plain))  # plain: metres from one pair
    for c in robust:  # symmetric positive semi-definite
        assert np.allclose(c, c.T) and np.linalg.eigvalsh(c).min() >= -1e-12


def test_an_estimate_off_the_fit_carries_its_displacement(rng):
    pos, r = network(rng, outlier_m=0.0)
    est = pos.copy()
    est[5] += (0.6, -0.4)  # node 5 off by 0.72 m, the others at the truth
    cov = position_covariance(r, est, (0, 1, 2), robust_scale=0.3)
    assert np.trace(cov[5]) >= 0.6**2 + 0.4**2 - 0.05
    e = est[5] - pos[5]
    assert e @ np.linalg.solve(cov[5], e) <= 5.991  # the truth inside its 95 % ellipse
    i, j = np.triu_indices(len(pos), 1)
    z = np.median(r[:, i, j], axis=0)
    free = np.flatnonzero(np.r_[[False, False, True, False], np.ones(2 * len(pos) - 4, bool)])
    fit = polish(est, i, j, z, free, 0.3)
    assert np.abs(fit - pos).max() < 0.1  # the fit returns to the pairs' positions


def test_an_estimate_in_a_wrong_basin_is_measured_against_the_ranges_fit(rng):
    """A filter that diverged (nodes swapped, metres off): polishing from its estimate stays in the wrong
    basin; `robust_fit` also starts from the pairs' MDS layout and keeps the lower cost, so every node's
    displacement from the fit, and the truth, is in its covariance."""
    from jaxcal.mesh.pair_covariance import robust_fit

    pos, r = network(rng, outlier_m=0.0)
    est = pos.copy()
    est[3:] = pos[np.r_[4 : len(pos), 3]]  # nodes 3.. each at the next one's place
    i, j = np.triu_indices(len(pos), 1)
    z = np.median(r[:, i, j], axis=0)
    free = np.flatnonzero(np.r_[[False, False, True, False], np.ones(2 * len(pos) - 4, bool)])
    assert np.abs(polish(est, i, j, z, free, 0.3) - pos).max() > 1.0  # polish alone: the wrong basin
    assert np.abs(robust_fit(est, i, j, z, free, 0.3, (0, 1, 2)) - pos).max() < 0.1
    cov = position_covariance(r, est, (0, 1, 2), robust_scale=0.3)
    e = est[3:] - pos[3:]
    assert np.all(np.trace(cov[3:], axis1=1, axis2=2) >= 0.9 * np.sum(e * e, axis=1))  # metres off, metres wide
    nees = [ek @ np.linalg.solve(ck, ek) for ek, ck in zip(e, cov[3:], strict=True)]
    assert np.median(nees) <= 5.991  # most truths inside their 95 % ellipse (the fit's own error is ~5 % outside)


def test_network_displacement_is_a_shared_variance_and_a_gross_node_keeps_its_own(rng):
    """`displacement="network"` (what pgp and parametric report): the mean square of the free coordinates'
    displacements on every free coordinate, written out here; a node metres off (beyond the 99.9 % chi-square
    quantile under the MAD scale) is left out of it and keeps its own d d^T. Displacements drawn from one
    Gaussian then land inside their 95 % ellipses about 95 % of the time (not 100 %, as with d d^T per node)."""
    from jaxcal.mesh.pair_covariance import _displacement_term

    n = 400
    dev = rng.normal(0.0, 0.2, (n, 2))
    mask = np.ones((n, 2), bool)
    mask[0] = False
    mask[1, 1] = False
    dev[~mask] = 0.0
    dev[7] = (3.0, -2.0)
    term = _displacement_term(dev, mask, "network")
    scale2 = (1.4826 * np.median(np.abs(dev[mask]))) ** 2
    gross = np.sum(dev**2, axis=1) / scale2 > chi2.ppf(0.999, mask.sum(axis=1).clip(1))
    gross[0] = False
    assert gross[7] and gross.sum() <= 4  # the node metres off; a Gaussian draw beyond 99.9 % is rare
    inl = mask & ~gross[:, None]
    var = np.mean(dev[inl] ** 2)
    for k in np.flatnonzero(~gross)[1:]:
        np.testing.assert_allclose(term[k], np.diag(np.where(mask[k], var, 0.0)), rtol=1e-12)
    np.testing.assert_array_equal(term[0], np.zeros((2, 2)))
    g = term[7]
    assert np.linalg.eigvalsh(g - np.outer(dev[7], dev[7])).min() >= -1e-12
    assert np.linalg.eigvalsh(g - var * np.eye(2)).min() >= -1e-12
    nees = np.array([dev[k] @ np.linalg.solve(term[k], dev[k]) for k in range(2, n)])
    assert 0.9 <= np.mean(nees <= 5.991) <= 0.99
