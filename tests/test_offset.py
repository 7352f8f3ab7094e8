"""The pose/range clock offset (`jaxcal.trajectory.offset` through `nls.prepare_offset`): recovered within its
reported standard deviation, NaN and not applied where the range rate cannot fix it, and its variance in the
anchors' covariance."""

from types import SimpleNamespace

import equinox as eqx
import numpy as np

from jaxcal import solver as S
from jaxcal.data import TrajectoryDataset
from jaxcal.precision import in_float64
from jaxcal.trajectory import common, nls, offset
from test_nls import lissajous
from trajectory_campaigns import one_anchor_dataset

prepare = in_float64(nls.prepare_offset)


def test_offset_recovered_within_its_sd(rng):
    shift = float(rng.uniform(-0.3, 0.3))
    ds = lissajous(noise=0.05, shift_s=shift, seed=int(rng.integers(1 << 30)), bias=0.2)
    _, info = prepare(ds, nls.NLSParams(estimate_offset=True))
    est, sd = info["time_offset_estimate_s"], info["time_offset_sd_s"]
    assert info["time_offset_s"] == est  # applied
    assert 0 < sd < 0.01, sd  # 2950 ranges of 5 cm noise at ~1 m/s fix it to milliseconds
    assert abs(est - shift) < 4 * sd, (est, shift, sd)


def spiral(rate_mps: float, seed: int) -> TrajectoryDataset:
    """A tag on an Archimedean spiral around one anchor in its plane: the range grows at a constant rate."""
    gen = np.random.default_rng(seed)
    t = np.arange(0.0, 60.0, 0.05)

    def body(tt):
        rho, phi = 5.0 + rate_mps * tt, 0.8 * tt
        return np.stack([rho * np.cos(phi), rho * np.sin(phi), np.zeros_like(tt)], 1), np.zeros_like(tt)

    rt = np.arange(1.0, 59.0, 0.02)
    r = np.interp(rt, t, 5.0 + rate_mps * t) + 0.02 * gen.normal(size=rt.size)
    return one_anchor_dataset("spiral", body, np.zeros((1, 3)), t, rt, r)


def test_constant_range_rate_gives_no_offset(rng, caplog):
    ds = spiral(0.05, int(rng.integers(1 << 30)))
    _, info = prepare(ds, nls.NLSParams(estimate_offset=True, time_offset_s=0.0))
    assert np.isnan(info["time_offset_estimate_s"]) and np.isnan(info["time_offset_sd_s"])
    assert info["time_offset_s"] == 0.0 and "offset_sensitivity" not in info  # not applied, nothing added
    assert "NaN" in caplog.text and "constant" in caplog.text


def test_offset_variance_enters_the_covariance(rng):
    ds = lissajous(noise=0.05, shift_s=0.1, seed=int(rng.integers(1 << 30)))
    _, info = prepare(ds, nls.NLSParams(estimate_offset=True))
    extra = common.offset_covariances(info, ds.n_anchors)
    s = np.asarray(info["offset_sensitivity"])
    np.testing.assert_allclose(extra, info["time_offset_sd_s"] ** 2 * np.einsum("ai,aj->aij", s, s))
    assert np.abs(s).max() > 0.1  # the anchors do move with the offset on this path
    plain = {"mirror_z": 0.0}  # no mirror-image check, whose widening comes after the sum
    on = nls.calibrate(ds, dict(plain, estimate_offset=True)).covariance
    # finish adds exactly that term to the covariance nls computes at the offset applied
    off = nls.calibrate(ds, dict(plain, estimate_offset=False, time_offset_s=info["time_offset_s"])).covariance
    np.testing.assert_allclose(on, off + extra, rtol=1e-6, atol=1e-12)


def test_retry_of_the_unconverged_anchors_alone_matches_retrying_all(rng):
    """`nls.solve_all_checked` retries only the anchors that ran out of steps; the slow reference retries the
    whole batch (`solver.retry_unconverged`). An anchor with exact ranges converges at once: a subset is retried.
    The retry gets 50 steps, so that every fit converges: at a step limit where a fit only just converges, the
    batch it runs in decides it (XLA sums a lane in another order; 14 of 20 seeds at 8 steps once the range
    arrays were padded to 1024)."""
    ds = lissajous(n_anchor=3, noise=0.05, outliers=40, seed=int(rng.integers(1 << 30)), bias=0.2)
    p = nls.NLSParams(estimate_offset=False, max_steps=2)
    groups, _ = in_float64(nls.prepare_poses)(ds, p)
    pos, rr, mask = (np.concatenate([x, x[:1]]) for x in (groups.position, groups.range, groups.mask))
    rr[-1] = np.linalg.norm(pos[-1] - np.array([1.0, 2.0, 2.5]), axis=-1)  # exact ranges: ls lands on it
    groups = SimpleNamespace(position=pos, range=rr, mask=mask)

    def full(steps):
        out = nls._solve_all(pos, rr, mask, eqx.tree_at(lambda q: q.max_steps, p, steps))
        return out, out[3]

    first = np.asarray(in_float64(full)(2)[1])
    assert first[-1] == S.CONVERGED and (first == S.MAX_STEPS).any(), first  # a strict subset is retried
    (fast, codes, steps) = in_float64(nls.solve_all_checked)(groups, p, factor=25)
    (ref, ref_codes, ref_steps) = in_float64(S.retry_unconverged)(full, 2, factor=25)
    assert steps == ref_steps == 50 and (np.asarray(codes) == S.CONVERGED).all()
    np.testing.assert_array_equal(codes, ref_codes)
    for a, b in zip(fast, ref, strict=True):  # converged fits in another batch: within 1e-8 m (20 seeds)
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-7, atol=1e-7, equal_nan=True)


def test_thinned_start_fit_gives_the_offset_of_the_full_one(rng):
    """`prepare_offset` seeds the joint fit with `nls` on a subsample (fast path); the reference seeds it with
    `nls` on every range. The joint fit refits the anchors, so the offset is the same up to a small part of its sd."""
    ds = lissajous(noise=0.05, shift_s=float(rng.uniform(-0.3, 0.3)), seed=int(rng.integers(1 << 30)), bias=0.2)
    p = nls.NLSParams(estimate_offset=True)
    _, fast = in_float64(nls.prepare_offset)(ds, p, 200)
    _, ref = in_float64(nls.prepare_offset)(ds, p, 0)
    sd = ref["time_offset_sd_s"]
    assert abs(fast["time_offset_estimate_s"] - ref["time_offset_estimate_s"]) < 0.05 * sd, (fast, ref)
    assert abs(fast["time_offset_sd_s"] - sd) < 0.05 * sd
    np.testing.assert_allclose(fast["offset_sensitivity"], ref["offset_sensitivity"], rtol=0.05, atol=1e-3)


def test_joint_fit_converges_to_the_same_offset_from_two_starts(rng):
    """The joint rounds stop on the step test (well below the cap), and where they stop hardly depends on the
    start: the estimate and its sd agree from the stated offset and from 0.15 s away (the Cauchy scales are
    frozen where the hold rounds end, which depends on the start: the estimates differed by up to 0.38 sd on
    seeds 0-19)."""
    shift = float(rng.uniform(-0.2, 0.2))
    ds = lissajous(noise=0.05, shift_s=shift, seed=int(rng.integers(1 << 30)), bias=0.2)
    _, a = prepare(ds, nls.NLSParams(estimate_offset=True, time_offset_s=0.0))
    _, b = prepare(ds, nls.NLSParams(estimate_offset=True, time_offset_s=0.15))
    assert 0 < a["time_offset_rounds"] < offset.MAX_ROUNDS and 0 < b["time_offset_rounds"] < offset.MAX_ROUNDS
    sd = a["time_offset_sd_s"]
    assert abs(a["time_offset_estimate_s"] - b["time_offset_estimate_s"]) < 0.5 * sd, (a, b)
    assert abs(a["time_offset_sd_s"] - b["time_offset_sd_s"]) < 0.15 * sd
    assert a["time_offset_stretch_p"] > offset.MIN_STRETCH_P  # one offset throughout: the Q test keeps it


def test_stretches_with_different_offsets_widen_the_offset_sd(rng, caplog):
    """The clock jumps by 0.1 s halfway (the ranges of the second half stamped later): the stretches disagree
    far beyond their sd, so their mean is applied with an sd widened to their spread (random effects), with
    one line; the jump's two offsets (0 and 0.1 s) are each within about two of those sd."""
    ds = lissajous(noise=0.05, seed=int(rng.integers(1 << 30)), bias=0.2)
    t = np.asarray(ds.range_time)
    ds = eqx.tree_at(lambda d: d.range_time, ds, np.where(t > 30.0, t + 0.1, t))
    _, steady = prepare(lissajous(noise=0.05, seed=1, bias=0.2), nls.NLSParams(estimate_offset=True))
    _, info = prepare(ds, nls.NLSParams(estimate_offset=True, time_offset_s=0.0))
    est, sd = info["time_offset_estimate_s"], info["time_offset_sd_s"]
    assert info["time_offset_stretch_p"] < offset.MIN_STRETCH_P
    assert np.isfinite(est) and info["time_offset_s"] == est
    assert sd > 3.0 * steady["time_offset_sd_s"], (sd, steady)
    assert abs(abs(est) - 0.05) < sd and 0.05 < 2.5 * sd, (est, sd)
    assert "disagree" in caplog.text and "widened" in caplog.text


def test_stated_pose_drift_widens_the_offset_sd(rng):
    ds = lissajous(noise=0.05, shift_s=0.1, seed=int(rng.integers(1 << 30)), bias=0.2)
    _, plain = prepare(ds, nls.NLSParams(estimate_offset=True))
    _, drift = prepare(ds, nls.NLSParams(estimate_offset=True, pose_drift=0.02))
    assert drift["time_offset_estimate_s"] == plain["time_offset_estimate_s"]  # the estimate is the same
    assert drift["time_offset_sd_s"] > 1.2 * plain["time_offset_sd_s"], (drift, plain)
