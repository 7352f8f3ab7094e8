"""The nls-seeded, bounded mean-model GP (`gp` default, `jaxcal.trajectory.gp_anchor`): its pieces
against direct NumPy / SciPy references, on 20 random draws where draws matter."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import multivariate_normal
from tests.test_gp import _matern_ref, drone

from jaxcal.trajectory import gp, gp_anchor

SEEDS = range(20)


def _spd(gen, scale=1.0):
    m = gen.normal(size=(3, 3))
    return scale * (m @ m.T + 0.1 * np.eye(3))


def _theta():
    hyper = gp.Hyper(jnp.log(1.2), jnp.log(0.3), jnp.log(0.05))
    return gp_anchor.MeanModel(jnp.array([0.3, -0.2, 1.5]), jnp.array(0.1), hyper)


def test_nlml_with_per_point_noise_equals_dense_scipy():
    gen = np.random.default_rng(1)
    n, pad = 15, 3
    x = gen.uniform(-3, 3, (n + pad, 3))
    r = gen.uniform(1.0, 6.0, n + pad)
    s = gen.uniform(1.0, 20.0, n + pad)
    mask = np.arange(n + pad) < n
    th = _theta()
    args = (jnp.asarray(x), jnp.asarray(r), jnp.asarray(mask), 1.5, 1e-6, "range", jnp.asarray(s))
    got = float(gp_anchor.mean_model_nlml(th, *args))
    xv, rv = x[:n], r[:n]
    d = np.linalg.norm(xv[:, None] - xv[None], axis=-1)
    k = _matern_ref(d, 1.2, 0.3, 1.5) + np.diag(0.05 * s[:n] + 1e-6 * 0.3)
    mean = np.linalg.norm(xv - np.asarray(th.anchor), axis=1) + 0.1
    assert got == pytest.approx(-multivariate_normal(mean=mean, cov=k).logpdf(rv), rel=1e-9)


def test_blocks_nlml_equals_dense_block_diagonal_scipy():
    """Blocks of consecutive ranges, independent: the log density of one Gaussian whose covariance
    is block-diagonal (a partly filled and an empty block included)."""
    gen = np.random.default_rng(2)
    n_blk, m = 3, 6
    x = gen.uniform(-3, 3, (n_blk, m, 3))
    r = gen.uniform(1.0, 6.0, (n_blk, m))
    s = gen.uniform(1.0, 5.0, (n_blk, m))
    mask = np.ones((n_blk, m), bool)
    mask[1, 4:] = False
    mask[2] = False
    th = _theta()
    got = float(gp_anchor.blocks_nlml(th, *(jnp.asarray(v) for v in (x, r, mask)), 1.5, 1e-6, "range", jnp.asarray(s)))
    ref = 0.0
    for b in range(n_blk):
        k = mask[b]
        if not k.any():
            continue
        xv, rv, sv = x[b, k], r[b, k], s[b, k]
        d = np.linalg.norm(xv[:, None] - xv[None], axis=-1)
        cov = _matern_ref(d, 1.2, 0.3, 1.5) + np.diag(0.05 * sv + 1e-6 * 0.3)
        mean = np.linalg.norm(xv - np.asarray(th.anchor), axis=1) + 0.1
        ref -= multivariate_normal(mean=mean, cov=cov).logpdf(rv)
    assert got == pytest.approx(ref, rel=1e-9)


def test_cauchy_weights_formula():
    e = np.array([0.0, 0.1, -0.2, 3.0, 0.05])
    c = 2.385 * 1.4826 * np.median(np.abs(e))
    np.testing.assert_allclose(gp_anchor.cauchy_weights(e), 1 / (1 + (e / c) ** 2))
    # the scale never drops below its floor
    np.testing.assert_allclose(gp_anchor.cauchy_weights(np.zeros(3) + 1e-9), 1.0, atol=1e-12)
    # center=True (the drift cells'): the scale from the MAD about the median
    c = 2.385 * 1.4826 * np.median(np.abs(e - np.median(e)))
    np.testing.assert_allclose(gp_anchor.cauchy_weights(e, center=True), 1 / (1 + (e / c) ** 2))


@pytest.mark.parametrize("seed", SEEDS)
def test_bound_step_stays_in_the_ellipsoid_along_the_step(seed):
    gen = np.random.default_rng(seed)
    a0, cov0, a = gen.normal(size=3), _spd(gen, 0.1), gen.normal(size=3) * 3
    k = 2.0
    b = gp_anchor.bound_step(a0, cov0, a, k)
    maha = lambda v: float(np.sqrt((v - a0) @ np.linalg.solve(cov0, v - a0)))  # noqa: E731
    assert maha(b) <= k + 1e-9
    if maha(a) <= k:
        np.testing.assert_allclose(b, a)
    else:
        assert maha(b) == pytest.approx(k)
        np.testing.assert_allclose(np.cross(b - a0, a - a0), 0.0, atol=1e-9)  # same direction
    np.testing.assert_allclose(gp_anchor.bound_step(a0, cov0, a, 0.0), a)  # 0 = unbounded


@pytest.mark.parametrize("seed", SEEDS)
def test_widen_covariance_dominates_both(seed):
    gen = np.random.default_rng(100 + seed)
    c, f = _spd(gen), _spd(gen)
    w = gp_anchor.widen_covariance(c, f)
    assert np.linalg.eigvalsh(w - c).min() > -1e-9
    assert np.linalg.eigvalsh(w - f).min() > -1e-9
    np.testing.assert_allclose(gp_anchor.widen_covariance(c, 0.5 * c), c, atol=1e-12)


def test_fuse_equals_scalar_precision_weighting():
    a0, a1 = np.array([0.0, 1.0, 2.0]), np.array([1.0, 3.0, 2.0])
    c0, c1 = np.diag([1.0, 4.0, 1.0]), np.diag([3.0, 4.0, 1.0])
    np.testing.assert_allclose(gp_anchor.fuse(a0, c0, a1, c1), [0.25, 2.0, 2.0])


def test_subsample_gp_is_bounded_by_nls_and_no_more_confident():
    """gp with model=subsample (the default before the fourteenth round): within max_shift_sigma of nls
    (Mahalanobis under nls's covariance; gp sizes its step by nls's narrower model covariance), and its
    covariance at least nls's in every direction. Without the mirror check's profile, which widens each
    method's covariance about its own estimate."""
    from jaxcal.trajectory import nls

    ds = drone(noise=0.05)
    res = gp.calibrate(ds, {"n_train": 60, "mirror_profile": 0, "model": "subsample"})
    ref = nls.calibrate(ds, {"mirror_profile": 0})
    assert res.params["mean"] == "anchor"
    for a in range(2):
        d = res.position[a] - ref.position[a]
        bound = res.params["max_shift_sigma"] ** 2 + 1e-6
        assert d @ np.linalg.solve(ref.covariance[a], d) <= bound
        assert np.linalg.eigvalsh(res.covariance[a] - ref.covariance[a]).min() > -1e-9


def test_hyper_penalty_is_zero_inside_the_bounds_and_quadratic_outside():
    h = gp.Hyper(jnp.log(5.0), jnp.log(0.01), jnp.log(0.1))
    assert float(gp_anchor.hyper_penalty(h, jnp.log(10.0), jnp.log(1e-3))) == 0.0
    out = gp.Hyper(jnp.log(10.0) + 0.5, jnp.log(1e-3) - 0.25, jnp.log(0.1))
    # 0.5 (0.5 / 0.25)^2 + 0.5 (0.25 / 0.25)^2
    assert float(gp_anchor.hyper_penalty(out, jnp.log(10.0), jnp.log(1e-3))) == pytest.approx(2.5)


def test_mean_model_fit_without_correlated_error_stays_inside_the_bounds(rng):
    """Ranges with white noise only: the marginal likelihood is largest at signal variance 0 (the
    unbounded BFGS walks log s^2 and then log l away, campus: s = 1e-5 m, l = 1e12 m); with the
    kernel's soft bounds the fit stays near the floor and the ceiling, and places the anchor."""
    import equinox as eqx

    n = 120
    t = np.linspace(0, 2 * np.pi, n)
    x = np.c_[20 * np.cos(t), 12 * np.sin(2 * t), 1.5 + 0.8 * np.sin(3 * t)] + rng.normal(0, 0.5, (n, 3))
    anchor = np.array([4.0, -3.0, 6.0]) + rng.normal(0, 1.0, 3)
    noise = 0.1
    r = np.linalg.norm(x - anchor, axis=1) + rng.normal(0, noise, n)
    xc = x - x.mean(axis=0)
    hyper = gp.Hyper(jnp.log(5.0), jnp.log(0.005), jnp.log(0.005))
    init = gp_anchor.MeanModel(jnp.asarray(anchor - x.mean(axis=0) + 0.2), jnp.array(0.0), hyper)
    radius = np.linalg.norm(xc, axis=1).max()
    floor = 1e-4 * noise**2
    bounds = (jnp.log(radius), jnp.log(floor))
    fit = eqx.filter_jit(gp_anchor._fit_mean_model)
    th, _, _ = fit(jnp.asarray(xc), jnp.asarray(r), jnp.ones(n, bool), init, 1.5, 1e-6, 200, "range", None, bounds)
    assert float(th.hyper.log_variance) > np.log(floor) - 1.0
    assert float(th.hyper.log_length) < np.log(radius) + 1.0
    est = np.asarray(th.anchor) + x.mean(axis=0)
    assert np.linalg.norm(est - anchor) < 0.5


def test_gp_adds_the_shared_pose_error_nls_estimates_and_keeps_positions(rng, caplog, monkeypatch):
    """gp (default model) on poses with a random-walk drift (the data of the test above, to share its compiled
    fit): with `estimate_drift` (the default) the estimate is made once, at nls's answer with nls's parameters (as
    nls makes it), its covariance is the one without plus a PSD term that grows an anchor, one warning line says
    so, and the positions are those without."""
    import logging

    import equinox as eqx

    from jaxcal.trajectory import drift, nls

    ds = drone(noise=0.05)
    gen = np.random.default_rng(rng)
    walk = np.cumsum(gen.normal(0.0, 0.05 * np.sqrt(0.05), (ds.pose_time.size, 2)), axis=0)
    pose = np.asarray(ds.pose_position).copy()
    pose[:, :2] += walk - walk[0]
    ds = eqx.tree_at(lambda d: d.pose_position, ds, pose)
    base = {"n_train": 60, "mirror_profile": 0}
    off = gp.calibrate(ds, {**base, "estimate_drift": False})
    assert "info_pose_error_model" not in off.params
    calls = []

    def spy(dataset, groups, est, bias, cov, p, method):
        calls.append((np.array(est), np.array(bias), p))
        return estimate(dataset, groups, est, bias, cov, p, method)

    estimate = drift.drift_for_covariance
    monkeypatch.setattr(drift, "drift_for_covariance", spy)
    with caplog.at_level(logging.WARNING, logger="jaxcal"):
        on = gp.calibrate(ds, base)
    lines = [r.getMessage() for r in caplog.records if "pose_drift not stated" in r.getMessage()]
    ref = nls.calibrate(ds, {"mirror_profile": 0, "estimate_drift": False})
    assert len(calls) == 1  # once
    est, bias, p = calls[0]
    np.testing.assert_allclose(est, ref.position, atol=1e-9)
    np.testing.assert_allclose(bias, ref.params["info_bias_m"], atol=1e-9)
    assert p == nls.NLSParams()  # nls's own: estimate_drift, drift_model, cov_clusters, min_scale_m
    np.testing.assert_array_equal(on.position, off.position)
    assert on.params["info_pose_error_propagated"]
    grown = []
    for a in range(2):
        c = on.covariance[a]
        np.testing.assert_allclose(c, c.T)
        assert np.linalg.eigvalsh(c).min() >= 0
        extra = c - off.covariance[a]
        assert np.linalg.eigvalsh(0.5 * (extra + extra.T)).min() > -1e-12
        grown.append(np.trace(extra[:2, :2]))
    assert max(grown) > 0
    assert len(lines) == (on.params["info_pose_error_widened"] > 1.005) and all(s.startswith("gp:") for s in lines)
    with pytest.raises(gp.JaxcalError, match="parameter drift_model: expected one of auto, drift, bounded"):
        gp.calibrate(ds, {"drift_model": "odometry"})
