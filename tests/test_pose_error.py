"""The stated pose error (`pose_sd_m`, `pose_drift`) propagated into the anchor covariance."""

import numpy as np
import pytest

from jaxcal.errors import JaxcalError
from jaxcal.trajectory import nls
from jaxcal.trajectory.pose_error import pose_error_covariance
from test_nls import lissajous


def _two_passes(gen, n=120):
    """An anchor passed twice, along two crossing roads over a hill (as on the simulated campaigns, small):
    range times, tag positions, anchor."""
    t = np.concatenate([np.linspace(10.0, 22.0, n), np.linspace(80.0, 92.0, n)])
    s = np.linspace(-12.0, 12.0, n)
    road = np.concatenate([np.column_stack([s, 0.0 * s]), np.column_stack([-3.0 + 0.0 * s, -s])])
    tags = np.column_stack([road + gen.normal(0.0, 0.1, (2 * n, 2)), 1.0 + 1.5 * np.exp(-((np.r_[s, s] / 6.0) ** 2))])
    anchor = np.array([1.5, 5.0, 4.0])
    return t, tags, anchor


def _reference(tags, rng, t, anchor, sd, drift, t0, bounded=(0.0, 1.0)):
    """The double sum over range pairs written out (n^2 kernel matrix), unit weights at the same estimate."""
    d = tags - anchor
    dist = np.linalg.norm(d, axis=1)
    u = d / dist[:, None]
    b = np.median(rng - dist)
    res = dist + b - rng
    scale = max(2.385 * 1.4826 * np.median(np.abs(res - np.median(res))), 0.05)
    w = 1.0 / (1.0 + (res / scale) ** 2)
    jac = np.column_stack([-u, np.ones(len(rng))])
    a_inv = np.linalg.inv((jac * w[:, None]).T @ jac)
    tau = t - t0
    k = sd**2 + drift**2 * np.minimum(tau[:, None], tau[None, :])
    k = k + bounded[0] ** 2 * np.exp(-np.abs(tau[:, None] - tau[None, :]) / bounded[1])
    m = np.zeros((4, 4))
    for i in range(len(rng)):
        for j in range(len(rng)):
            kij = k[i, j] * (u[i, :2] @ u[j, :2])  # independent horizontal axes: sum over h of u_ih u_jh
            m += w[i] * w[j] * kij * np.outer(jac[i], jac[j])
    return (a_inv @ m @ a_inv)[:3, :3]


def test_pose_error_covariance_equals_the_double_sum(rng):
    gen = np.random.default_rng(rng)
    t, tags, anchor = _two_passes(gen, n=40)
    r = np.linalg.norm(tags - anchor, axis=1) + 0.1 + gen.standard_t(3, t.size) * 0.05
    cases = ((0.0, 0.02, (0.0, 1.0)), (0.15, 0.0, (0.0, 1.0)), (0.1, 0.05, (0.0, 1.0)))
    # the bounded shared error (exponential kernel) over correlation times shorter than the gaps between ranges,
    # than a pass, than the two passes' separation, and with the other terms
    cases += ((0.0, 0.0, (0.2, 0.05)), (0.0, 0.0, (0.2, 4.0)), (0.0, 0.0, (0.1, 300.0)), (0.1, 0.02, (0.2, 30.0)))
    for sd, drift, bounded in cases:
        fast = pose_error_covariance(
            tags, r, t, anchor, sd, drift, t0=2.0, bounded_sd_m=bounded[0], bounded_corr_s=bounded[1]
        )
        ref = _reference(tags, r, t, anchor, sd, drift, 2.0, bounded)
        np.testing.assert_allclose(fast, ref, rtol=1e-9, atol=1e-10 * np.trace(ref))
        assert np.linalg.eigvalsh(fast).min() > -1e-12 * np.trace(fast)


def test_the_part_the_stretch_jackknife_cannot_see_equals_its_dense_expectation(rng):
    """`seen_by`: the propagated covariance less the expectation, under the same kernel, of the cluster jackknife
    over consecutive stretches of the linearised fit (`nls.robust_covariance`), written out with the n x n residual
    map and kernel matrix; the PSD part of the difference is returned."""
    gen = np.random.default_rng(rng)
    t, tags, anchor = _two_passes(gen, n=40)
    r = np.linalg.norm(tags - anchor, axis=1) + 0.1 + gen.standard_t(3, t.size) * 0.05
    d = tags - anchor
    u = d / np.linalg.norm(d, axis=1)[:, None]
    res = np.linalg.norm(d, axis=1) - r
    res = res - np.median(res)
    scale = max(2.385 * 1.4826 * np.median(np.abs(res - np.median(res))), 0.05)
    w = 1.0 / (1.0 + (res / scale) ** 2)
    jac = np.column_stack([-u, np.ones(t.size)])
    a = (jac * w[:, None]).T @ jac
    hat = jac @ np.linalg.solve(a, (jac * w[:, None]).T)  # the fit's share of each residual
    lab = (np.arange(t.size) * 4) // t.size
    # an error correlated over 4 s (within a stretch, about 6 s: the jackknife sees all of it), over 300 s (longer
    # than the two passes' separation: most is unseen), an offset with a drift (the offset is never seen)
    cases = (
        ((0.0, 0.0, (0.2, 4.0)), 0.0, 1e-9),
        ((0.0, 0.0, (0.1, 300.0)), 0.4, 0.95),
        ((0.1, 0.03, (0.0, 1.0)), 0.25, 0.7),
    )
    for (sd, drift, bounded), lo, hi in cases:
        tau = t - 2.0
        k = sd**2 + drift**2 * np.minimum(tau[:, None], tau[None, :])
        k = k + bounded[0] ** 2 * np.exp(-np.abs(tau[:, None] - tau[None, :]) / bounded[1])
        k = k * (u[:, :2] @ u[:, :2].T)
        lev = np.linalg.solve(a, (jac * w[:, None]).T)  # (4, n): how each range's error moves the fit
        full = lev @ k @ lev.T
        seen = np.zeros((4, 4))
        for g in range(4):
            a_g = (jac[lab == g] * w[lab == g, None]).T @ jac[lab == g]
            pick = (jac * (w * (lab == g))[:, None]).T  # (4, n): stretch g's score of the residuals
            step = np.linalg.solve(a - a_g, pick @ (np.eye(t.size) - hat))
            seen += 0.75 * step @ k @ step.T
        lam, vec = np.linalg.eigh((full - seen)[:3, :3])
        ref = (vec * np.maximum(lam, 0.0)) @ vec.T
        fast = pose_error_covariance(
            tags, r, t, anchor, sd, drift, 2.0, bounded_sd_m=bounded[0], bounded_corr_s=bounded[1], seen_by=4
        )
        np.testing.assert_allclose(fast, ref, rtol=1e-7, atol=1e-9 * np.trace(full))
        assert lo <= np.trace(fast[:2, :2]) / np.trace(full[:2, :2]) < hi


def _fit(tags, r, x0):
    """Gauss-Newton range fit with a bias (unit weights): what the propagation linearises."""
    x = np.concatenate([x0, [0.0]])
    for _ in range(20):
        d = tags - x[:3]
        dist = np.linalg.norm(d, axis=1)
        jac = np.column_stack([-d / dist[:, None], np.ones(len(r))])
        x = x - np.linalg.lstsq(jac, dist + x[3] - r, rcond=None)[0]
    return x[:3]


def test_drift_propagation_matches_the_spread_of_refits_under_simulated_drift(rng):
    """Monte Carlo: reported tag positions = true + a horizontal random walk from t0 (plus an offset); the
    refits' covariance over 400 draws is the propagated one (within the sampling error of 400 draws)."""
    gen = np.random.default_rng(rng)
    t, tags, anchor = _two_passes(gen)
    r = np.linalg.norm(tags - anchor, axis=1)  # exact ranges: the only error is the pose error
    sd, drift, t0 = 0.02, 0.01, 0.0  # small enough for the linearisation (at 0.05, 0.03: 24 % more in y)
    pred = pose_error_covariance(tags, r, t, anchor, sd, drift, t0)
    fits = []
    for _ in range(400):
        steps = gen.normal(0.0, 1.0, (t.size, 2)) * drift * np.sqrt(np.diff(np.concatenate([[t0], t])))[:, None]
        delta = np.cumsum(steps, axis=0) + gen.normal(0.0, sd, 2)
        fits.append(_fit(tags + np.column_stack([delta, np.zeros(t.size)]), r, anchor))
    emp = np.cov(np.array(fits).T)
    # horizontal block: the propagated variances hold the refits' spread to within 20 % (400 draws: about 7 % sd)
    for v in (np.array([1.0, 0.0]), np.array([0.0, 1.0]), np.array([1.0, 1.0]) / np.sqrt(2)):
        assert 0.8 < (v @ emp[:2, :2] @ v) / (v @ pred[:2, :2] @ v) < 1.25
    assert np.trace(pred[:2, :2]) > (sd**2 + drift**2 * 50.0)  # at least the pose error at the passes' mean time


def test_bounded_error_propagation_matches_the_spread_of_refits(rng):
    """Monte Carlo for the bounded shared error: reported tag positions = true + a stationary (Ornstein-Uhlenbeck)
    horizontal error of sd s and correlation time T, drawn exactly at the range times; the refits' covariance over
    400 draws is the propagated one (within the sampling error), and it is below s^2 where T is short against the
    passes (the fit averages the error) and near s^2 where T is long (the error moves the anchor whole)."""
    gen = np.random.default_rng(rng)
    t, tags, anchor = _two_passes(gen)
    r = np.linalg.norm(tags - anchor, axis=1)
    s = 0.02
    for corr_s, lo, hi in ((3.0, 0.02, 0.6), (600.0, 0.7, 1.5)):
        pred = pose_error_covariance(tags, r, t, anchor, 0.0, 0.0, 0.0, bounded_sd_m=s, bounded_corr_s=corr_s)
        decay = np.exp(-np.diff(t, prepend=t[0]) / corr_s)
        fits = []
        for _ in range(400):
            kick = gen.normal(0.0, s, (t.size, 2)) * np.sqrt(1.0 - decay**2)[:, None]
            delta = np.zeros((t.size, 2))
            delta[0] = gen.normal(0.0, s, 2)
            for i in range(1, t.size):
                delta[i] = decay[i] * delta[i - 1] + kick[i]
            fits.append(_fit(tags + np.column_stack([delta, np.zeros(t.size)]), r, anchor))
        emp = np.cov(np.array(fits).T)
        # 400 draws: about 7 % sd per variance; 120 such checks over seeds 0-19, so a band of 4.5 sd (seed 4 drew
        # 0.75 at T = 3 s; 2000 draws on that seed give 0.98-1.00)
        for v in (np.array([1.0, 0.0]), np.array([0.0, 1.0]), np.array([1.0, 1.0]) / np.sqrt(2)):
            assert 0.7 < (v @ emp[:2, :2] @ v) / (v @ pred[:2, :2] @ v) < 1.4, (corr_s, v)
        assert lo * s**2 < np.trace(pred[:2, :2]) / 2 < hi * s**2, (corr_s, np.trace(pred[:2, :2]) / 2 / s**2)
        assert np.linalg.eigvalsh(pred).min() > -1e-12 * np.trace(pred)


def test_stated_pose_error_widens_nls_covariance_by_the_propagated_term():
    ds = lissajous(noise=0.05, seed=3)
    base = nls.calibrate(ds, {"mirror_profile": 0, "estimate_drift": False})
    wide = nls.calibrate(ds, {"mirror_profile": 0, "pose_sd_m": 0.2, "pose_drift": 0.01})
    np.testing.assert_allclose(wide.position, base.position)
    for a in range(3):
        extra = wide.covariance[a] - base.covariance[a]
        assert np.linalg.eigvalsh(extra).min() > -1e-12
        # a shared offset of 0.2 m per axis moves the anchor with it: at least that much horizontally
        assert np.diag(extra)[:2].min() > 0.5 * 0.2**2
        assert np.linalg.eigvalsh(wide.covariance[a]).min() >= 0


def test_nls_widens_by_the_estimated_pose_error_states_it_and_keeps_positions(caplog):
    """nls with `estimate_drift` (`jaxcal.trajectory.drift`; here to share the compiled fit of the test above): a
    drift of 0.05 m/sqrt(s) on the poses is found (the model propagated, a drift's upper bound or a bounded shared
    error's, is positive; the covariance grows by a PSD term; one warning line says so); positions are those of
    the run without the estimate; a stated `pose_drift` is used as it is."""
    import logging

    import equinox as eqx

    from jaxcal.trajectory.drift import drift_for_covariance

    ds = lissajous(noise=0.05, seed=3)
    gen = np.random.default_rng(7)
    walk = np.cumsum(gen.normal(0.0, 0.05 * np.sqrt(0.05), (ds.pose_time.size, 2)), axis=0)
    pose = np.asarray(ds.pose_position).copy()
    pose[:, :2] += walk - walk[0]
    ds = eqx.tree_at(lambda d: d.pose_position, ds, pose)
    off = nls.calibrate(ds, {"mirror_profile": 0, "estimate_drift": False})
    with caplog.at_level(logging.WARNING, logger="jaxcal"):
        on = nls.calibrate(ds, {"mirror_profile": 0, "estimate_drift": True})
    np.testing.assert_allclose(on.position, off.position)
    upper = on.params["info_pose_drift_upper"]
    assert upper >= on.params["info_pose_drift_estimate"] >= 0 and upper > 0.01
    assert on.params["pose_drift"] == 0  # an estimate is not a statement: the extra covariance carries it
    if on.params["info_pose_error_model"] == "bounded":  # its sd's upper bound, over a time up to the path's span
        assert on.params["info_pose_bounded_sd_m"] > 0.05
        assert 0 < on.params["info_pose_bounded_corr_s"] <= float(np.ptp(np.asarray(ds.pose_time)))
    assert sum("pose_drift not stated" in r.getMessage() for r in caplog.records) == 1
    assert on.params["info_pose_error_widened"] > 1.005
    grown = []
    for a in range(3):
        extra = on.covariance[a] - off.covariance[a]
        assert np.linalg.eigvalsh(0.5 * (extra + extra.T)).min() > -1e-12
        np.testing.assert_allclose(on.covariance[a], on.covariance[a].T)
        grown.append(np.trace(extra[:2, :2]))
    assert max(grown) > 0  # the part of the walk that nls's stretch jackknife cannot see
    # a statement wins: no estimate
    told_p = (nls.NLSParams(pose_drift=0.02, estimate_drift=True), nls.NLSParams(pose_sd_m=0.1, drift_model="drift"))
    for stated in told_p:
        assert drift_for_covariance(ds, None, None, None, None, stated, "nls") == (stated, {}, None)
    # the user names the pose source's kind (`drift_model`): that model is propagated, whatever fits better
    for kind in ("drift", "bounded"):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="jaxcal"):
            told = nls.calibrate(ds, {"mirror_profile": 0, "drift_model": kind})  # turns the estimate on
        np.testing.assert_allclose(told.position, off.position)
        assert told.params["info_pose_error_model"] == kind
        lines = [r.getMessage() for r in caplog.records if "pose_drift not stated" in r.getMessage()]
        assert len(lines) == 1 and f"drift_model={kind}" in lines[0]
        assert told.params["pose_drift"] == 0
        if kind == "drift":
            assert told.params["info_pose_drift_upper"] > 0.01
        else:
            assert told.params["info_pose_bounded_sd_m"] > 0
    with pytest.raises(JaxcalError, match="parameter drift_model: expected one of auto, drift, bounded"):
        nls.calibrate(ds, {"estimate_drift": True, "drift_model": "odometry"})


@pytest.mark.parametrize("bad", [{"pose_sd_m": -0.1}, {"pose_drift": float("nan")}])
def test_negative_pose_error_is_refused(bad):

    with pytest.raises(JaxcalError, match=f"parameter {next(iter(bad))}: must be"):
        nls.NLSParams(**bad)


def test_cli_stated_pose_error_then_evaluate_prints_horizontal_and_vertical_apart(tmp_path):
    from conftest import run_cli
    from jaxcal.io import hdf5

    ds = lissajous(noise=0.05, seed=1)
    f, out = tmp_path / "liss.h5", tmp_path / "R.h5"
    hdf5.write(f, ds)
    proc = run_cli("calibrate", f, "--method", "nls", "-o", out, "--set", "pose_sd_m=0.1", "--set", "pose_drift=0.01")
    assert proc.returncode == 0, proc.stderr
    assert "poses taken as exact" not in proc.stdout + proc.stderr  # the error was stated
    res = hdf5.read(out)  # written, so every finite block passed the writer's symmetric-PSD check
    assert np.isfinite(res.covariance).all() and (np.diagonal(res.covariance, axis1=1, axis2=2)[:, :2] > 0.01).all()
    ev = run_cli("evaluate", out, "--truth", f)
    assert ev.returncode == 0, ev.stderr
    lines = ev.stdout.splitlines()
    for part in ("horizontal", "vertical"):
        line = next(x for x in lines if x.strip().startswith(part))
        assert "predicted rms" in line and "actual" in line and "NEES per coordinate" in line and "coverage" in line


def test_range_times_are_those_of_the_grouping_or_of_the_dataset_when_a_method_regroups():
    from jaxcal.trajectory.pose_error import anchor_times
    from jaxcal.trajectory.poses import AnchorRanges, prepare_poses

    ds = lissajous(seed=2)
    groups, _ = prepare_poses(ds, nls.NLSParams())
    kept = anchor_times(ds, groups)
    regrouped = anchor_times(ds, AnchorRanges(groups.position, groups.range, groups.mask))  # as gp passes them
    for a in range(3):
        np.testing.assert_array_equal(kept[a], ds.range_time[ds.range_anchor == a])
        np.testing.assert_array_equal(regrouped[a], kept[a])


def test_calibrate_says_when_a_trajectory_covariance_takes_the_poses_as_exact():
    from jaxcal.commands.calibrate import _pose_error_stated

    assert not _pose_error_stated({}) and not _pose_error_stated({"pose_drift": 0.0, "pose_sd_m": "0"})
    assert _pose_error_stated({"pose_drift": 0.02}) and _pose_error_stated({"pose_sd_m": "0.1"})
    assert not _pose_error_stated({"pose_drift": "x"})  # not a number: the parameter check reports it
