"""The pose/range clock offset (`jaxcal.trajectory.offset` through `nls.prepare_offset`): recovered within its
reported standard deviation, NaN and not applied where the range rate cannot fix it, and its variance in the
anchors' covariance."""

import numpy as np

from jaxcal.data import TrajectoryDataset
from jaxcal.precision import in_float64
from jaxcal.trajectory import common, nls
from test_nls import lissajous

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
    rho, phi = 5.0 + rate_mps * t, 0.8 * t
    pos = np.stack([rho * np.cos(phi), rho * np.sin(phi), np.zeros_like(t)], 1)
    rt = np.arange(1.0, 59.0, 0.02)
    r = np.interp(rt, t, rho) + 0.02 * gen.normal(size=rt.size)
    return TrajectoryDataset(
        name="spiral",
        anchor_ids=["a0"],
        tag_ids=["t"],
        lever_arm=[[0.0, 0.0, 0.0]],
        pose_time=t,
        pose_position=pos,
        range_time=rt,
        range_anchor=np.zeros(rt.size, int),
        range_tag=np.zeros(rt.size, int),
        range=r,
        anchor_truth=np.zeros((1, 3)),
    )


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
