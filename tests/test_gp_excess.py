"""The one-sided NLOS excess (`gp` with `model=excess`, `jaxcal.trajectory.gp_excess`): its skewed density against
SciPy's, and on a simulated campaign with an NLOS zone (a place where every range carries a positive excess) an
anchor error below the symmetric robust fit's (any seed)."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.stats import exponnorm

from jaxcal.errors import JaxcalError
from jaxcal.trajectory import gp_excess


def test_emg_logpdf_equals_scipy_exponnorm():
    x = np.linspace(-1.0, 6.0, 57)
    for mu, sigma, tau in [(0.0, 0.08, 0.12), (0.4, 0.1, 2.5), (-0.2, 0.5, 0.01)]:
        ref = exponnorm.logpdf(x, tau / sigma, loc=mu, scale=sigma)
        got = np.asarray(gp_excess.emg_logpdf(jnp.asarray(x), mu, sigma, tau))
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9)


def _zone_campaign(rng, n_laps: int = 3):
    """Laps of a 40 x 30 m rectangle climbing 0-3 m (height observable), an anchor beside it, and an NLOS zone:
    every range taken with the tag east of x = 20 m carries +0.4 m (+-0.1) and, one in three, an exponential
    excess of mean 1 m; elsewhere LOS (N(0, 0.05^2)); range bias 0.2 m."""
    s = np.linspace(0.0, 1.0, 400, endpoint=False)
    corners = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 30.0], [0.0, 30.0], [0.0, 0.0]])
    edge = np.linspace(0.0, 4.0, 5)
    xy = np.stack([np.interp(s * 4.0, edge, corners[:, d]) for d in range(2)], axis=1)
    pos = []
    for lap in range(n_laps):
        z = 1.5 + 1.5 * np.sin(2.0 * np.pi * (s + lap / n_laps))
        pos.append(np.c_[xy + rng.normal(0.0, 0.3, xy.shape), z])
    pos = np.concatenate(pos)
    anchor = np.array([rng.uniform(5.0, 15.0), rng.uniform(8.0, 22.0), rng.uniform(3.0, 5.0)])
    dist = np.linalg.norm(pos - anchor, axis=1)
    zone = pos[:, 0] > 20.0
    excess = (
        0.4 + 0.1 * rng.standard_normal(dist.size) + (rng.random(dist.size) < 1 / 3) * rng.exponential(1.0, dist.size)
    )
    r = dist + 0.2 + 0.05 * rng.standard_normal(dist.size) + np.where(zone, excess, 0.0)
    return pos, r, anchor


def _cauchy_fit(pos, r, x0):
    """The symmetric robust fit (nls's model r = |p - a| + b with a Cauchy loss)."""
    sol = least_squares(lambda x: np.linalg.norm(pos - x[:3], axis=1) + x[3] - r, x0, loss="cauchy", f_scale=0.15)
    return sol.x


def test_one_sided_excess_beats_the_symmetric_fit_in_an_nlos_zone(rng):
    pos, r, anchor = _zone_campaign(rng)
    start = np.r_[anchor + rng.normal(0.0, 0.5, 3), 0.0]
    sym = _cauchy_fit(pos, r, start)
    n = r.size
    cells = np.floor((pos[:, :2] - pos[:, :2].min(axis=0)) / 40.0 * 16).clip(0, 15).astype(int)
    labels = cells[:, 0] * 16 + cells[:, 1]
    out = gp_excess.fit_excess_all(
        *(jnp.asarray(v)[None] for v in (pos, r, np.ones(n, bool), labels, sym[:3])),
        jnp.asarray(sym[3:4]),
        jnp.asarray([True]),
        256,
        8,
        5.0,
        200,
    )
    err_sym = np.linalg.norm(sym[:3] - anchor)
    err_exc = np.linalg.norm(np.asarray(out[0][0]) - anchor)
    assert err_exc < 0.7 * err_sym, (err_exc, err_sym)
    # the covariance is a covariance and not absurd (within a factor 100 of the error's scale)
    cov = np.asarray(out[1][0])
    assert np.all(np.linalg.eigvalsh(cov) > 0) and np.trace(cov) < 100.0 * max(err_sym, 0.05) ** 2


def test_excess_parameters_are_checked():
    from jaxcal.sim.trajectory import simulate
    from jaxcal.trajectory import gp

    # checked whatever the model: with model=subsample they were ignored silently (a negative count accepted)
    for model in ("excess", "subsample"):
        for bad in ({"excess_rounds": 0}, {"excess_rounds": -1}, {"excess_max_ranges": -1}, {"excess_cells": 0}):
            with pytest.raises(JaxcalError, match="excess_rounds >= 1"):
                gp.calibrate(simulate("small", seed=0), {"model": model, **bad})


def _zone_fit_args(rng):
    pos, r, anchor = _zone_campaign(rng, n_laps=2)
    n = r.size
    cells = np.floor((pos[:, :2] - pos[:, :2].min(axis=0)) / 40.0 * 16).clip(0, 15).astype(int)
    start = np.r_[anchor + rng.normal(0.0, 0.3, 3), 0.2]
    args = (pos, r, np.ones(n, bool), cells[:, 0] * 16 + cells[:, 1], start[:3])
    return [jnp.asarray(v)[None] for v in args] + [jnp.asarray(start[3:4]), jnp.asarray([True])], anchor


def test_newton_started_em_equals_the_identity_started_one(rng):
    """The fast path (each round's BFGS started from the exact inverse Hessian, `solver.StartedBFGS`) stops at the
    same minimum per round as BFGS from the identity (the EM of the thirteenth round): the same anchor within
    1 mm after every round's M-step, the same covariance."""
    args, _ = _zone_fit_args(rng)
    fast = gp_excess.fit_excess_all(*args, 256, 4, 5.0, 200)
    ref = gp_excess.fit_excess_all(*args, 256, 4, 5.0, 200, None, False)
    assert np.all(np.asarray(fast[4]) == 0) and np.all(np.asarray(ref[4]) == 0)
    np.testing.assert_allclose(np.asarray(fast[0]), np.asarray(ref[0]), atol=1e-3)
    np.testing.assert_allclose(np.asarray(fast[1]), np.asarray(ref[1]), rtol=1e-2, atol=1e-9)


def test_em_on_every_range_by_index_equals_the_em_without_indices(rng):
    """`sub` listing every range (thin_indices with k = 0 or k above the count) is the fit on all of them, within
    rounding (gathered, the sums run in another order: 1.9e-9 relative apart on the VM of 2026-11-29)."""
    args, _ = _zone_fit_args(rng)
    mask = np.asarray(args[2])
    full = gp_excess.fit_excess_all(*args, 256, 2, 5.0, 200)
    for k in (0, mask.shape[1] + 5):
        sub = jnp.asarray(gp_excess.thin_indices(mask, k))
        got = gp_excess.fit_excess_all(*args, 256, 2, 5.0, 200, sub)
        for a, b in zip(got[:3], full[:3], strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-7, atol=1e-10)


def test_thin_indices_are_evenly_spaced_valid_ranges():
    mask = np.zeros((3, 50), bool)
    mask[0, :40] = True
    mask[1, ::2] = True  # 25 valid
    idx = gp_excess.thin_indices(mask, 10)
    assert idx.shape == (3, 10)
    assert idx[0, 0] == 0 and idx[0, -1] == 39 and np.all(np.diff(idx[0]) >= 4)
    assert np.all(mask[1, idx[1]]) and idx[1, -1] == 48
    assert np.all(idx[2] == -1)  # no valid range: padding only
    np.testing.assert_array_equal(gp_excess.thin_indices(mask, 0)[1, :25], np.arange(0, 50, 2))
