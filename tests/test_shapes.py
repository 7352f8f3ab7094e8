"""jaxcal.shapes: padded lengths, and trajectory fits on padded arrays equal to the fits on exact ones."""

import logging

import numpy as np
import pytest

from jaxcal.methods import calibrate
from jaxcal.shapes import exact_lengths, padded_length
from jaxcal.sim.trajectory import simulate


def test_padded_lengths_cover_n_with_at_most_a_quarter_more_on_a_coarse_ladder():
    n = np.arange(1, 20_001)
    out = np.array([padded_length(k) for k in n])
    assert (out >= n).all() and (out[4:] <= 1.25 * n[4:]).all()
    assert (np.diff(out) >= 0).all()
    assert np.unique(out).size < 60  # 20,000 lengths share a few dozen shapes
    with exact_lengths():
        assert [padded_length(k) for k in (1, 430, 513)] == [1, 430, 513]
    assert padded_length(430) == 448  # and back outside


@pytest.mark.parametrize(
    ("method", "seed", "drift", "tol_m"),
    [("nls", 1, 0.02, 1e-6), ("ls", 0, 0.0, 1e-6), ("gp", 0, 0.0, 2e-3)],
)
def test_fits_on_padded_arrays_equal_the_fits_on_exact_ones(method, seed, drift, tol_m):
    """Padding (mask False) changes no estimate, covariance or NaN: the per-anchor ranges, the offset's fit, the
    EM's thinned ranges and the route cells. Iterative solvers end within rounding (gp's BFGS: 0.2 mm, measured)."""
    logging.getLogger("jaxcal").setLevel(logging.ERROR)
    ds = simulate("small", seed=seed, drift=drift)
    padded = calibrate(ds, method)
    with exact_lengths():
        exact = calibrate(ds, method)
    np.testing.assert_array_equal(np.isnan(padded.position), np.isnan(exact.position))
    np.testing.assert_allclose(padded.position, exact.position, atol=tol_m, rtol=0)
    scale = np.nanmax(np.abs(exact.covariance))
    np.testing.assert_allclose(padded.covariance, exact.covariance, atol=tol_m * scale, rtol=1e-3)
