"""The path GP (`gp` with `model=path`, `jaxcal.trajectory.gp_path`): the Kalman-filter likelihood against
the dense Matern covariance and a SciPy Cholesky, and the fit on random draws (any seed)."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import cho_factor, cho_solve
from scipy.stats import chi2
from tests.test_gp import drone

from jaxcal.errors import JaxcalError
from jaxcal.methods import calibrate
from jaxcal.trajectory import gp_path
from jaxcal.trajectory.gp_kernel import Hyper


def _dense_nlml(s, y, noise, length, var, nu):
    """-log N(y; 0, K), K = Matern(|s_i - s_j|) + diag(noise), by a SciPy Cholesky (the slow reference)."""
    d = np.abs(s[:, None] - s[None, :])
    z = np.sqrt(2.0 * nu) * d / length
    k = var * (1.0 + z if nu == 1.5 else 1.0) * np.exp(-z) + np.diag(noise)
    c = cho_factor(k, lower=True)
    return 0.5 * y @ cho_solve(c, y) + np.sum(np.log(np.diag(c[0]))) + 0.5 * y.size * np.log(2.0 * np.pi)


@pytest.mark.parametrize("nu", [0.5, 1.5])
def test_kalman_nlml_equals_dense_cholesky(nu, rng):
    n, pad = 60, 4
    s = np.sort(rng.uniform(0.0, 30.0, n + pad))
    s[20] = s[19]  # a standstill: two ranges at the same place on the path
    s[n:] = s[n - 1]
    y = rng.normal(size=n + pad)
    scale = rng.uniform(1.0, 10.0, n + pad)
    mask = np.arange(n + pad) < n
    length, var, noise = rng.uniform(0.5, 5.0), rng.uniform(0.1, 1.0), rng.uniform(0.01, 0.2)
    h = Hyper(jnp.log(length), jnp.log(var), jnp.log(noise))
    got = float(gp_path.kalman_nlml(h, jnp.asarray(s), jnp.asarray(y), jnp.asarray(mask), nu, jnp.asarray(scale)))
    ref = _dense_nlml(s[:n], y[:n], noise * scale[:n], length, var, nu)
    assert got == pytest.approx(ref, rel=1e-6, abs=1e-6)


def test_path_nlml_is_the_dense_density_of_the_range_model(rng):
    n = 50
    x = np.cumsum(rng.normal(0.0, 0.3, (n, 3)), axis=0)
    s = np.asarray(gp_path.arc_length(jnp.asarray(x), jnp.ones(n, bool)))
    assert s == pytest.approx(np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(x, axis=0), axis=1))])
    a, b = np.array([2.0, -1.0, 3.0]), 0.15
    r = np.linalg.norm(x - a, axis=1) + b + rng.normal(0.0, 0.3, n)
    th = gp_path.PathModel(jnp.asarray(a), jnp.asarray(b), Hyper(jnp.log(2.0), jnp.log(0.05), jnp.log(0.01)))
    got = float(gp_path.path_nlml(th, jnp.asarray(x), jnp.asarray(s), jnp.asarray(r), jnp.ones(n, bool), 1.5))
    y = r - np.linalg.norm(x - a, axis=1) - b
    assert got == pytest.approx(_dense_nlml(s, y, np.full(n, 0.01), 2.0, 0.05, 1.5), rel=1e-6)


def test_fit_recovers_anchor_under_correlated_error_with_honest_covariance(rng):
    """A 3-D path around two anchors, range errors a random walk along the path (sd 0.1 m per sqrt(10 m))
    plus white noise: the fit lands within 0.5 m and inside its own covariance's 1e-4 chi^2 region."""
    n, a_n = 600, 2
    anchors = np.array([[0.0, 0.0, 2.0], [8.0, 3.0, 1.0]])
    t = np.linspace(0.0, 60.0, n)
    path = np.stack([6.0 * np.cos(0.3 * t), 6.0 * np.sin(0.2 * t), 1.5 * np.sin(0.5 * t)], 1)
    x = np.stack([path + anchors[k] for k in range(a_n)])
    step = np.linalg.norm(np.diff(x, axis=1), axis=2)
    walk = np.cumsum(np.c_[np.zeros(a_n), rng.normal(size=(a_n, n - 1)) * np.sqrt(step / 10.0) * 0.1], axis=1)
    r = np.linalg.norm(x - anchors[:, None], axis=2) + 0.3 + walk + rng.normal(0.0, 0.03, (a_n, n))
    a0 = anchors + rng.normal(0.0, 0.3, (a_n, 3))
    out = gp_path.fit_path_all(
        *(jnp.asarray(v) for v in (x, r, np.ones((a_n, n), bool), np.ones((a_n, n)), a0, np.zeros(a_n))),
        1.5,
        400,
        1e-4,
        1.0,
    )
    est, cov = np.asarray(out[0]), np.asarray(out[1])
    for k in range(a_n):
        e = est[k] - anchors[k]
        assert np.linalg.norm(e) < 0.5
        assert e @ np.linalg.solve(cov[k], e) < chi2.ppf(1 - 1e-4, 3)


def test_gp_path_noise_free_within_5cm():
    ds = drone()
    res = calibrate(ds, "gp", {"model": "path"})
    assert np.linalg.norm(res.position - ds.anchor_truth, axis=1).max() < 0.05
    assert res.params["info_model"] == "path"


@pytest.mark.parametrize(
    "bad", [{"model": "dense"}, {"model": "path", "nu": 2.5}, {"model": "path", "mean": "constant"}]
)
def test_gp_path_bad_settings_are_clear_errors(bad):
    with pytest.raises(JaxcalError, match="model"):
        calibrate(drone(), "gp", bad)
