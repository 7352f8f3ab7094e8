"""NLS / LS baselines, clock-offset search and the CLI path of the trajectory methods."""

import numpy as np
import pytest
import scipy.linalg

from conftest import run_cli
from jaxcal.data import TrajectoryDataset
from jaxcal.io import hdf5
from jaxcal.trajectory import common, ls, nls
from jaxcal.trajectory.poses import estimate_time_offset, fit_poses


def lissajous(n_anchor=3, noise=0.0, planar=False, outliers=0, shift_s=0.0, seed=0, bias=0.0):
    """Tag on a 3-D (or planar) Lissajous with yaw rotation and a lever arm; ranges round-robin."""
    rng = np.random.default_rng(seed)
    anchors = rng.uniform([-4, -4, 2.0], [4, 4, 3.0], (n_anchor, 3))

    def body(t):
        zamp = 0.0 if planar else 1.2
        p = np.stack([5 * np.sin(0.31 * t), 5 * np.sin(0.23 * t + 1), zamp * np.sin(0.17 * t) + 1.0], 1)
        return p, 0.1 * t

    t = np.arange(0, 60.0, 0.05)
    p, yaw = body(t)
    q = np.stack([0 * t, 0 * t, np.sin(yaw / 2), np.cos(yaw / 2)], 1)
    rt = np.arange(0.5, 59.5, 0.02)
    pr, yr = body(rt)
    c, s = np.cos(yr), np.sin(yr)
    tag = pr + np.stack([c * 0.3 - s * 0.1, s * 0.3 + c * 0.1, 0.2 + 0 * rt], 1)
    ai = np.arange(rt.size) % n_anchor
    r = np.linalg.norm(tag - anchors[ai], axis=1) + bias + noise * rng.normal(size=rt.size)
    if outliers:
        r[rng.choice(rt.size, outliers, replace=False)] += rng.uniform(5, 25, outliers)
    return TrajectoryDataset(
        name="liss",
        anchor_ids=[f"a{i}" for i in range(n_anchor)],
        tag_ids=["t"],
        lever_arm=[[0.3, 0.1, 0.2]],
        pose_time=t,
        pose_position=p,
        pose_orientation=q,
        range_time=rt - shift_s,
        range_anchor=ai,
        range_tag=np.zeros(rt.size, int),
        range=r,
        anchor_truth=anchors,
    )


def _err(res, ds):
    return np.linalg.norm(res.position - ds.anchor_truth, axis=1)


def test_ls_exact_on_noise_free_data():
    ds = lissajous()
    res = ls.calibrate(ds)
    assert _err(res, ds).max() < 1e-5
    assert res.method == "ls" and res.covariance.shape == (3, 3, 3)


def test_ls_planar_recovers_height_above_plane():
    ds = lissajous(planar=True)  # anchors above the tag plane: the default side
    res = ls.calibrate(ds)
    assert _err(res, ds).max() < 1e-4


def test_nls_noise_free_within_5cm_and_bias_recovered():
    ds = lissajous(bias=0.3)
    res = nls.calibrate(ds)
    assert _err(res, ds).max() < 0.05
    np.testing.assert_allclose(res.params["info_bias_m"], 0.3, atol=0.01)


def test_nls_robust_to_gross_outliers():
    ds = lissajous(noise=0.05, outliers=40)
    e_nls = _err(nls.calibrate(ds), ds)
    e_l2 = _err(nls.calibrate(ds, {"loss": "l2"}), ds)
    assert e_nls.max() < 0.1, e_nls
    assert e_l2.max() > 2 * e_nls.max()  # the robust loss is what helps


def test_nls_covariance_reflects_noise():
    lo = nls.calibrate(lissajous(noise=0.02, seed=1))
    hi = nls.calibrate(lissajous(noise=0.2, seed=1))
    sd_lo = np.sqrt(np.trace(lo.covariance, axis1=1, axis2=2))
    sd_hi = np.sqrt(np.trace(hi.covariance, axis1=1, axis2=2))
    assert np.all(sd_hi > 5 * sd_lo)


def test_time_offset_recovered():
    ds = lissajous(noise=0.02, shift_s=0.25)  # range clock runs 0.25 s behind the poses
    off = estimate_time_offset(fit_poses(ds), ds, max_offset_s=1.0)
    assert off == pytest.approx(0.25, abs=0.02)


def test_unknown_loss_is_a_clear_error():
    from jaxcal.errors import JaxcalError

    with pytest.raises(JaxcalError, match="loss"):
        nls.calibrate(lissajous(), {"loss": "tukey"})


def test_cli_calibrate_gp_then_evaluate(tmp_path):
    ds = lissajous(n_anchor=2)
    f = tmp_path / "liss.h5"
    hdf5.write(f, ds)
    out = tmp_path / "R.h5"
    env = {"XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}
    proc = run_cli(
        "calibrate",
        f,
        "--method",
        "gp",
        "-o",
        out,
        "--set",
        "n_train=60",
        "--set",
        "stages=1",
        env=env,
    )
    assert proc.returncode == 0, proc.stderr
    res = hdf5.read(out)
    assert res.method == "gp" and res.covariance.shape == (2, 3, 3)
    assert np.linalg.norm(res.position - ds.anchor_truth, axis=1).max() < 1.0  # tiny training set
    ev = run_cli("evaluate", out, "--truth", f, "--json")
    assert ev.returncode == 0, ev.stderr
    assert '"mean_error_m"' in ev.stdout
    # a bad --set is one line on stderr: test_batch's CLI test (`--set loss=tukey`, the same JaxcalError path
    # in the CLI) and `test_unknown_loss_is_a_clear_error` (nls's own check) cover it without a third process


def test_robust_covariance_equals_leave_one_stretch_out_refits_and_contains_the_model(rng):
    n, p, g = 60, 4, 6
    jac = rng.normal(size=(n, p))
    # errors correlated within stretches: a common shift per stretch of 10 consecutive entries
    res = rng.normal(size=n) * 0.05 + np.repeat(rng.normal(size=g), n // g) * 0.3
    mask = np.ones(n, bool)
    mask[-4:] = False  # padding at the end
    # residuals at a least-squares fit are orthogonal to the Jacobian's columns
    res[:56] -= jac[:56] @ np.linalg.lstsq(jac[:56], res[:56], rcond=None)[0]
    model = 0.01 * np.linalg.inv(jac.T @ jac)
    out = np.asarray(nls.robust_covariance(model, jac * mask[:, None], res * mask, mask, g))
    # reference: the linear fit refitted without each stretch (clusters by rank among the 56 valid entries);
    # for a linear model one Gauss-Newton step is the exact leave-one-out fit
    cl = (np.arange(56) * g) // 56
    y = jac[:56] @ np.ones(p) - res[:56]  # data whose fit is theta = 1 with residuals res (model - data)
    full = np.linalg.lstsq(jac[:56], y, rcond=None)[0]
    steps = np.stack([np.linalg.lstsq(jac[:56][cl != c], y[cl != c], rcond=None)[0] - full for c in range(g)])
    jack = (g - 1) / g * steps.T @ steps
    for part in (model, jack):
        assert np.linalg.eigvalsh(out - part).min() > -1e-12
    lam, vec = np.linalg.eigh(jack - model)
    np.testing.assert_allclose(out, model + (vec * np.maximum(lam, 0)) @ vec.T, atol=1e-10)
    # a stretch that the fit absorbs shows less in the residuals than it moves the fit: the jackknife is
    # at least the plain sandwich here (stretch leverage 1 / 6 on average)
    s = np.stack([(jac[:56][cl == c] * res[:56][cl == c, None]).sum(0) for c in range(g)])
    a_inv = np.linalg.inv(jac[:56].T @ jac[:56])
    sand = (g - 1) / g * a_inv @ s.T @ s @ a_inv
    assert np.trace(jack) > np.trace(sand)


def test_height_from_a_flat_path_is_nan_with_one_warning_line(caplog):
    from types import SimpleNamespace

    t = np.linspace(0, 2 * np.pi, 400)
    flat = np.stack([5 * np.cos(t), 5 * np.sin(2 * t), 0 * t], 1)
    hilly = flat + np.stack([0 * t, 0 * t, 1.5 * np.sin(3 * t)], 1)
    # an anchor near the plane of a flat path: its height enters the ranges only to second order
    # (h / r small everywhere) and trades off with the range bias; 3 m above it, it is fixed
    low, high = np.array([1.0, 1.0, 0.1]), np.array([8.0, 0.0, 3.0])
    assert common.height_dop_ratio(flat, low) > 10 > 5 * common.height_dop_ratio(flat, high)
    pos = np.stack([flat, flat, hilly])
    est = np.stack([low, high, low])
    rng = np.linalg.norm(pos - est[:, None], axis=-1)
    groups = SimpleNamespace(position=pos, range=rng, mask=np.ones(rng.shape, bool))
    p = nls.NLSParams()
    flag, zstd = common.unobservable_height(groups, est, p)
    assert flag.tolist() == [True, False, False] and zstd[0] == 0.0
    ds = SimpleNamespace(anchor_ids=["low", "high", "hilly"], name="t")
    with caplog.at_level("WARNING", logger="jaxcal"):
        res = common.finish(ds, "nls", p, groups, est, np.repeat(np.eye(3)[None], 3, 0) * 0.01, {})
    assert np.isnan(res.position[0, 2]) and np.isfinite(res.position[0, :2]).all()
    assert np.isnan(res.covariance[0, 2]).all() and np.isfinite(res.covariance[0, :2, :2]).all()
    assert np.isfinite(res.position[1:]).all()
    assert len(caplog.records) == 1 and "(low)" in caplog.text and "\n" not in caplog.records[0].getMessage()
    assert res.params["info_unobservable_height"] == ["low"]


def test_covariance_at_the_fit_is_nls_covariance_and_its_parts_are_narrower():
    """`covariances_at` at nls's fit with nls's stretch counts gives the covariance nls reports; the model
    covariance (gp's default `bound_clusters=0`) is no wider in any direction, and a single jackknife is
    at least the model covariance. (The single jackknife need not be below the reported one: each widening
    raises the covariance to another, and no smallest covariance above two exists in general.)"""
    import jax.numpy as jnp

    from jaxcal.trajectory.poses import prepare_poses

    ds = lissajous(noise=0.05, outliers=20, seed=3)
    p = nls.NLSParams()
    groups, _ = prepare_poses(ds, p)
    (est, cov, bias, _), _, _ = nls.solve_all_checked(groups, p)
    x4 = jnp.concatenate([est, bias[:, None]], axis=1)
    args = (groups.position, groups.range, groups.mask, x4, p)
    np.testing.assert_allclose(nls.covariances_at(*args, (p.cov_clusters, p.n_clusters)), cov, rtol=1e-8, atol=1e-14)
    model = np.asarray(nls.covariances_at(*args, ()))
    for a in range(3):
        assert np.linalg.eigvalsh(model[a]).min() > 0
        assert np.linalg.eigvalsh(np.asarray(cov[a]) - model[a]).min() > -1e-12 * np.trace(model[a])
        for part in ((16,), (4,)):
            jack = np.asarray(nls.covariances_at(*args, part))[a]
            assert np.linalg.eigvalsh(jack - model[a]).min() > -1e-12 * np.trace(model[a])


def test_start_fit_without_covariance_is_the_same_fit():
    """`with_cov=False` (the clock offset's start fit, `prepare_offset`) compiles the fit without the jackknifes:
    the anchors and biases are those of the full program (bit for bit: the same operations), the covariances NaN."""
    from jaxcal.trajectory.poses import prepare_poses

    ds = lissajous(noise=0.05, outliers=20, seed=3)
    p = nls.NLSParams()
    groups, _ = prepare_poses(ds, p)
    (est, _, bias, codes), _, _ = nls.solve_all_checked(groups, p)
    (est0, cov0, bias0, codes0), _, _ = nls.solve_all_checked(groups, p, with_cov=False)
    np.testing.assert_array_equal(np.asarray(est0), np.asarray(est))
    np.testing.assert_array_equal(np.asarray(bias0), np.asarray(bias))
    np.testing.assert_array_equal(np.asarray(codes0), np.asarray(codes))
    assert np.isnan(np.asarray(cov0)).all()


@pytest.mark.parametrize(
    "bad",
    [{"mirror_profile": -3}, {"mirror_z": -1.0}, {"side": 0.0}, {"min_ranges": 0}, {"max_gap_s": float("nan")}],
)
def test_trajectory_params_refuse_values_that_mean_nothing(bad):
    from jaxcal.errors import JaxcalError

    with pytest.raises(JaxcalError, match=f"parameter {next(iter(bad))}: must be"):
        nls.NLSParams(**bad)
    nls.NLSParams(mirror_z=0.0, mirror_profile=0)  # the documented "off" values stay valid


def test_a_stretch_that_holds_a_direction_has_its_leverage_capped_not_an_exploding_refit(rng):
    # stretch 0 alone holds (almost) all the information on parameter 0: leaving it out, that parameter is
    # all but undetermined and the explicit refit moves it by ~1 / (1 - leverage)
    n, p, g = 48, 3, 4
    jac = rng.normal(size=(n, p))
    cl = (np.arange(n) * g) // n
    jac[cl != 0, 0] *= 1e-4
    res = rng.normal(size=n) * 0.05 + np.repeat(rng.normal(size=g), n // g) * 0.3
    res -= jac @ np.linalg.lstsq(jac, res, rcond=None)[0]  # residuals at the least-squares fit
    mask = np.ones(n, bool)
    out = np.asarray(nls.robust_covariance(np.zeros((p, p)), jac, res, mask, g))
    # slow references: explicit leave-one-stretch-out refits of the linear problem (exact for a linear model)
    y = jac @ np.ones(p) - res
    full = np.linalg.lstsq(jac, y, rcond=None)[0]
    refit = np.stack([np.linalg.lstsq(jac[cl != c], y[cl != c], rcond=None)[0] - full for c in range(g)])
    # ... and the capped step written out: A_g's generalized eigenvalues against A clipped at MAX_LEVERAGE
    a = jac.T @ jac
    capped, lev = [], []
    for c in range(g):
        jg = jac[cl == c]
        mu, q = scipy.linalg.eigh(jg.T @ jg, a)  # q^T a q = I, so A_g = a q diag(mu) q^T a
        lev.append(mu.max())
        ag = a @ q @ np.diag(np.minimum(mu, nls.MAX_LEVERAGE)) @ q.T @ a
        capped.append(np.linalg.solve(a - ag, jg.T @ res[cl == c]))
    assert lev[0] > 0.999 and max(lev[1:]) < nls.MAX_LEVERAGE  # only stretch 0 is capped
    ref = (g - 1) / g * np.stack(capped).T @ np.stack(capped)
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-12)
    # the stretches under the cap are the explicit refits, unchanged
    np.testing.assert_allclose(np.stack(capped)[1:], refit[1:], rtol=1e-6, atol=1e-12)
    # leaving out stretch 0 explodes in the refit, not in the capped jackknife: in the norm of A, its step is
    # at most 1 / (1 - 0.99) = 100 times its plain step A^-1 s_0
    plain = np.linalg.solve(a, jac[cl == 0].T @ res[cl == 0])
    a_norm = lambda x: float(np.sqrt(x @ a @ x))  # noqa: E731
    assert a_norm(capped[0]) <= 100 * a_norm(plain) * (1 + 1e-9)
    assert a_norm(refit[0]) > 5 * a_norm(capped[0])
    assert np.isfinite(out).all() and np.linalg.eigvalsh(out).min() > -1e-12
