"""GP anchor calibration: kernel and likelihood against dense SciPy references, gradients,
accuracy."""

import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.special import gamma, kv
from scipy.stats import multivariate_normal

from jaxcal.data import TrajectoryDataset
from jaxcal.errors import JaxcalError
from jaxcal.trajectory import gp


def _matern_ref(r, length, var, nu):
    z = np.sqrt(2 * nu) * r / length
    with np.errstate(invalid="ignore", divide="ignore"):
        k = var * 2 ** (1 - nu) / gamma(nu) * z**nu * kv(nu, z)
    return np.where(z > 0, k, var)


@pytest.mark.parametrize("nu", [0.5, 1.5, 2.5, 5.0 / 3.0, 0.7])
def test_matern_matches_scipy_bessel(nu):
    r = np.concatenate([[0.0, 1e-9, 1e-4], np.linspace(0.01, 40.0, 2000)])
    got = np.asarray(gp.matern(jnp.asarray(r**2), 2.0, 1.7, nu))
    # closed forms to round-off; the series / asymptotic switch of the general form to ~1e-9
    np.testing.assert_allclose(got, _matern_ref(r, 2.0, 1.7, nu), atol=1e-8, rtol=0)


def test_integer_nu_rejected():
    with pytest.raises(JaxcalError, match="nu"):
        gp.matern(jnp.zeros(2), 1.0, 1.0, 2.0)


@pytest.mark.parametrize("nu", [1.5, 5.0 / 3.0])
def test_nlml_equals_dense_scipy(nu):
    rng = np.random.default_rng(1)
    n, pad = 25, 5
    x = rng.uniform(-3, 3, (n + pad, 3))
    y = rng.normal(size=n + pad)
    mask = np.arange(n + pad) < n
    h = gp.Hyper(jnp.log(1.3), jnp.log(0.8), jnp.log(0.05))
    got = float(gp.neg_log_marginal_likelihood(h, jnp.asarray(x), jnp.asarray(y), jnp.asarray(mask), nu, 1e-6))
    xv, yv = x[:n], y[:n]
    d = np.linalg.norm(xv[:, None] - xv[None], axis=-1)
    k = _matern_ref(d, 1.3, 0.8, nu) + (0.05 + 1e-6 * 0.8) * np.eye(n)
    ref = -multivariate_normal(mean=np.zeros(n), cov=k).logpdf(yv)
    assert got == pytest.approx(ref, rel=1e-9)


@pytest.mark.parametrize("nu", [1.5, 5.0 / 3.0])
def test_nlml_gradients(nu):
    rng = np.random.default_rng(2)
    x = jnp.asarray(rng.uniform(-2, 2, (12, 3)))
    y = jnp.asarray(rng.normal(size=12))
    mask = jnp.asarray(np.arange(12) < 10)
    h = gp.Hyper(jnp.log(1.1), jnp.log(0.9), jnp.log(0.1))
    check_grads(lambda h: gp.neg_log_marginal_likelihood(h, x, y, mask, nu), (h,), order=1, modes=("rev",))


def test_target_transform_roundtrip():
    r = jnp.array([0.1, 1.0, 7.5, 120.0])
    for t in ("range", "inv-log"):
        np.testing.assert_allclose(gp.from_target(gp.to_target(r, t), t), r, rtol=1e-10)


def test_stratified_subsample_covers_every_stratum():
    rng = np.random.default_rng(3)
    r = np.concatenate([rng.uniform(0, 10, 2000), rng.uniform(90, 100, 20)])  # far ranges are rare
    idx = gp.stratified_subsample(r, 100, 10, seed=0)
    assert idx.size == 100 and np.unique(idx).size == 100
    assert np.sum(r[idx] > 90) == 10  # the rare stratum keeps its full quota


def drone(noise=0.0, seed=0):
    """A drone inspecting two anchors in turn (3-D Lissajous around each); noise-free by default."""
    rng = np.random.default_rng(seed)
    anchors = np.array([[0.0, 0.0, 2.0], [10.0, 3.0, 2.5]])

    def path(t):
        k = (t >= 30).astype(int)
        s = t - 30 * k
        off = np.stack([1.5 * np.sin(0.9 * s), 1.5 * np.sin(0.7 * s + 0.5), 1.2 * np.sin(1.1 * s + 1.0)], 1)
        return anchors[k] + off + np.array([0.2, -0.1, 0.1]), k

    t = np.arange(0, 60.0, 0.05)
    rt = np.arange(0.01, 59.9, 0.1)
    p, k = path(rt)
    r = np.linalg.norm(p - anchors[k], axis=1) + noise * rng.normal(size=rt.size)
    return TrajectoryDataset(
        name="drone",
        anchor_ids=["a", "b"],
        tag_ids=["t"],
        lever_arm=np.zeros((1, 3)),
        pose_time=t,
        pose_position=path(t)[0],
        range_time=rt,
        range_anchor=k,
        range_tag=np.zeros(rt.size, int),
        range=r,
        anchor_truth=anchors,
    )


def test_gp_noise_free_within_5cm():
    ds = drone()
    res = gp.calibrate(ds, {"n_train": 120})
    err = np.linalg.norm(res.position - ds.anchor_truth, axis=1)
    assert np.all(err < 0.05), err
    assert res.covariance.shape == (2, 3, 3) and res.frame == "world"
    assert np.all(np.linalg.eigvalsh(res.covariance) > 0)


def test_gp_bad_target_is_a_clear_error():
    with pytest.raises(JaxcalError, match="target"):
        gp.calibrate(drone(), {"target": "log"})


# ------------------------------------------------------------------- parametric mean (mean=anchor)


def _theta():
    return gp.MeanModel(
        jnp.array([0.3, -0.2, 1.5]),
        jnp.array(0.1),
        gp.Hyper(jnp.log(1.2), jnp.log(0.3), jnp.log(0.05)),
    )


@pytest.mark.parametrize("target", ["range", "inv-log"])
def test_mean_model_nlml_equals_dense_scipy(target):
    rng = np.random.default_rng(4)
    n, pad = 20, 4
    x = rng.uniform(-3, 3, (n + pad, 3))
    r = rng.uniform(1.0, 6.0, n + pad)
    mask = np.arange(n + pad) < n
    th = _theta()
    got = float(gp.mean_model_nlml(th, jnp.asarray(x), jnp.asarray(r), jnp.asarray(mask), 1.5, 1e-6, target))
    xv, rv = x[:n], r[:n]
    d = np.linalg.norm(xv[:, None] - xv[None], axis=-1)
    k = _matern_ref(d, 1.2, 0.3, 1.5) + (0.05 + 1e-6 * 0.3) * np.eye(n)
    mean = np.linalg.norm(xv - np.asarray(th.anchor), axis=1) + 0.1
    tt = (lambda v: v) if target == "range" else (lambda v: 1.0 / np.log10(np.sqrt(v) + 1.0))
    ref = -multivariate_normal(mean=tt(mean), cov=k).logpdf(tt(rv))
    assert got == pytest.approx(ref, rel=1e-9)


def test_mean_model_nlml_gradients():
    rng = np.random.default_rng(5)
    x = jnp.asarray(rng.uniform(-2, 2, (12, 3)))
    r = jnp.asarray(rng.uniform(1.0, 4.0, 12))
    mask = jnp.asarray(np.arange(12) < 10)
    check_grads(lambda th: gp.mean_model_nlml(th, x, r, mask), (_theta(),), order=1, modes=("rev",))


def test_gp_anchor_mean_noise_free_within_5cm():
    ds = drone()
    res = gp.calibrate(ds, {"n_train": 80, "mean": "anchor", "model": "subsample"})
    err = np.linalg.norm(res.position - ds.anchor_truth, axis=1)
    assert np.all(err < 0.05), err
    assert np.all(np.linalg.eigvalsh(res.covariance) > 0)


def test_gp_anchor_mean_beats_paper_variant_under_correlated_bias():
    """Spatially smooth positive range bias (NLOS-like) plus white noise: the mean-model GP does
    at least as well as the paper's constant-mean GP with the cuboid search."""
    ds = drone()
    rng = np.random.default_rng(6)
    p = np.asarray(ds.pose_position)
    rt, pt = ds.range_time, ds.pose_time
    pr = np.column_stack([np.interp(rt, pt, p[:, d]) for d in range(3)])
    bias = 0.15 * (1.0 + np.sin(1.3 * pr[:, 0]) * np.cos(0.9 * pr[:, 1]))
    ds = eqx_replace(ds, range=ds.range + bias + 0.02 * rng.normal(size=rt.size))
    errs = {}
    for mean in ("constant", "anchor"):
        res = gp.calibrate(ds, {"n_train": 80, "mean": mean, "model": "subsample"})
        errs[mean] = np.linalg.norm(res.position - ds.anchor_truth, axis=1).mean()
    assert errs["anchor"] <= errs["constant"], errs


def eqx_replace(ds, **kw):
    fields = {k: getattr(ds, k) for k in ds.__dataclass_fields__}
    fields.update(kw)
    return TrajectoryDataset(**fields)


def test_gp_bad_mean_is_a_clear_error():
    with pytest.raises(JaxcalError, match="mean"):
        gp.calibrate(drone(), {"mean": "linear"})


# ------------------------------------------------------------------ search=gradient (eikonal step)


def trolley(noise=0.0, seed=0):
    """A planar trolley (z = 0) mowing a 10 x 8 m floor; anchor `in` 2 m above the floor, anchor
    `out` 6 m beyond its east edge (outside the covered region) and 2.5 m up."""
    rng = np.random.default_rng(seed)
    anchors = np.array([[4.0, 3.5, 2.0], [16.0, 4.0, 2.5]])
    t = np.arange(0.0, 80.0, 0.05)
    x = 5.0 + 5.0 * np.sin(2 * np.pi * t / 20.0)  # east-west sweeps
    y = 4.0 + 4.0 * np.sin(2 * np.pi * t / 80.0 - np.pi / 2)  # slow drift north and back
    pose = np.stack([x, y, np.zeros_like(t)], 1)
    rt = np.arange(0.02, 79.9, 0.1)
    k = np.arange(rt.size) % 2
    pr = np.stack([np.interp(rt, t, pose[:, d]) for d in range(3)], 1)
    r = np.linalg.norm(pr - anchors[k], axis=1) + noise * rng.normal(size=rt.size)
    return TrajectoryDataset(
        name="trolley",
        anchor_ids=["in", "out"],
        tag_ids=["t"],
        lever_arm=np.zeros((1, 3)),
        pose_time=t,
        pose_position=pose,
        range_time=rt,
        range_anchor=k,
        range_tag=np.zeros(rt.size, int),
        range=r,
        anchor_truth=anchors,
    )


def test_gradient_search_finds_anchor_outside_covered_region():
    """The cuboid search can only return points where the GP has data (its mean reverts to the
    constant far away); the eikonal step extrapolates from the data to an anchor 6 m outside."""
    ds = trolley(noise=0.02)
    errs = {}
    for search in ("cuboid", "gradient"):
        res = gp.calibrate(ds, {"n_train": 100, "mean": "constant", "search": search})
        errs[search] = np.linalg.norm(res.position - ds.anchor_truth, axis=1)
    assert errs["gradient"][0] < 0.3, errs  # anchor above the covered floor
    assert errs["gradient"][1] < 1.0, errs  # anchor 6 m outside it
    assert errs["cuboid"][1] > 3.0, errs  # the paper's search cannot leave the data
    assert np.all(np.linalg.eigvalsh(res.covariance) > 0)


def _post_numpy(x, y, length, var, noise, nu):
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    k = _matern_ref(d, length, var, nu) + noise * np.eye(len(x))
    alpha = np.linalg.solve(k, y)

    def mean(q):
        return _matern_ref(np.linalg.norm(q[None] - x, axis=-1), length, var, nu) @ alpha

    return mean


@pytest.mark.parametrize("planar", [False, True])
def test_gradient_step_equals_numpy_finite_differences(planar):
    """gradient_step against a dense NumPy posterior mean differentiated by central differences."""
    rng = np.random.default_rng(7)
    n, k = 40, 5
    x = rng.uniform(-4, 4, (n, 3))
    if planar:
        x[:, 2] = 0.0
    anchor = np.array([1.0, -0.5, 2.0])
    r = np.linalg.norm(x - anchor, axis=1) + 0.05 * rng.normal(size=n)
    mean_r = r.mean()
    h = gp.Hyper(jnp.log(3.0), jnp.log(4.0), jnp.log(0.01))
    mask = jnp.ones(n, bool)
    post = gp._posterior(h, jnp.asarray(x), jnp.asarray(r - mean_r), mask, mean_r, 1.5, 0.0)
    est, cov, _ = gp.gradient_step(post, jnp.asarray(x), mask, "range", k, jnp.asarray(planar), 1.0)
    f = _post_numpy(x, r - mean_r, 3.0, 4.0, 0.01, 1.5)
    rh = np.array([f(q) for q in x]) + mean_r
    top = np.argsort(rh)[:k]
    cands = []
    for i in top:
        e = 1e-5
        g = np.array([(f(x[i] + e * u) - f(x[i] - e * u)) / (2 * e) for u in np.eye(3)])
        if planar:
            gxy = g[:2] / max(1.0, np.linalg.norm(g[:2]))
            z = rh[i] * np.sqrt(max(1.0 - gxy @ gxy, 0.0))
            cands.append(np.r_[x[i, :2] - rh[i] * gxy, x[i, 2] + z])
        else:
            cands.append(x[i] - rh[i] * g / np.linalg.norm(g))
    cands = np.array(cands)
    np.testing.assert_allclose(np.asarray(est), cands.mean(0), atol=1e-6)
    np.testing.assert_allclose(np.asarray(cov), np.cov(cands.T), atol=1e-6)


def test_gp_bad_search_is_a_clear_error():
    with pytest.raises(JaxcalError, match="search"):
        gp.calibrate(drone(), {"search": "grid"})


def test_range_consistency_equals_numpy():
    rng = np.random.default_rng(8)
    n = 30
    x = rng.uniform(-4, 4, (n + 3, 3))
    r = rng.uniform(1.0, 6.0, n + 3)
    mask = np.arange(n + 3) < n
    h = gp.Hyper(jnp.log(2.0), jnp.log(1.5), jnp.log(0.05))
    post = gp._posterior(h, jnp.asarray(x), jnp.asarray(r - 3.0), jnp.asarray(mask), 3.0, 1.5, 0.0)
    a = np.array([0.5, 1.0, 2.0])
    got = float(gp.range_consistency(post, jnp.asarray(x), jnp.asarray(mask), "range", a))
    f = _post_numpy(x[:n], r[:n] - 3.0, 2.0, 1.5, 0.05, 1.5)
    e = np.array([f(q) + 3.0 for q in x[:n]]) - np.linalg.norm(x[:n] - a, axis=1)
    assert got == pytest.approx(np.median(np.abs(e - np.median(e))), abs=1e-9)


def test_cone_spread_ignores_a_constant_bias():
    rng = np.random.default_rng(9)
    pos = rng.uniform(-5, 5, (1, 50, 3))
    a = np.array([[1.0, 2.0, 3.0]])
    r = np.linalg.norm(pos - a[:, None], axis=-1) + 0.4
    mask = np.ones((1, 50), bool)
    assert gp.cone_spread(pos, r, mask, a)[0] == pytest.approx(0.0, abs=1e-12)
    assert gp.cone_spread(pos, r, mask, a + 1.0)[0] > 0.1
    assert np.isnan(gp.cone_spread(pos, r, np.zeros((1, 50), bool), a)[0])


def test_anchor_mean_falls_back_to_nls_when_geometry_is_worse():
    """With a zero tolerance every anchor falls back: the result is the nls estimate exactly."""
    from jaxcal.trajectory import nls

    ds = drone(noise=0.05)
    res = gp.calibrate(ds, {"n_train": 40, "mean": "anchor", "max_spread_ratio": 1e-9})
    ref = nls.calibrate(ds)
    assert res.params["info_fallback_nls"] == [True, True]
    np.testing.assert_allclose(res.position, ref.position, atol=1e-9)
