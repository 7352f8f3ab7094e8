"""Simulated trajectory scenarios."""

import numpy as np
import pytest

from jaxcal.sim.trajectory import SCENARIOS, campus_layout, simulate


def test_campus_shape_and_determinism():
    a = simulate("campus", seed=3)
    b = simulate("campus", seed=3)
    assert a.n_anchors == 10 and "campus" in SCENARIOS
    np.testing.assert_array_equal(a.range, b.range)
    span = np.ptp(a.anchor_truth[:, :2], axis=0)
    assert 400 < span[0] <= 620 and 250 < span[1] <= 470  # spread over the 600 x 450 m campus
    dt = np.diff(a.pose_time)
    assert np.allclose(dt, 0.1)  # 10 Hz poses
    assert np.all(np.bincount(a.range_anchor, minlength=10) > 100)  # the route passes every anchor
    assert 0.0 < a.range_los.mean() < 1.0  # buildings make some links NLOS


def test_ranges_respect_geometry():
    ds = simulate("small", seed=1)
    los = ds.range_los == 1
    # true distance from the (exact) poses: LOS errors are small except rare outliers
    p = np.stack([np.interp(ds.range_time, ds.pose_time, ds.pose_position[:, d]) for d in range(3)], 1)
    d = np.linalg.norm(p - ds.anchor_truth[ds.range_anchor], axis=1)
    err = ds.range - d
    assert np.median(np.abs(err[los])) < 0.6  # lever arm (<1 m) + LOS channel error
    assert d.max() < 12.5 + 1.0  # max range scaled with the scenario (120 m x 0.1)


def test_drift_moves_poses_not_ranges():
    a = simulate("small", seed=2)
    b = simulate("small", seed=2, drift=0.05)
    np.testing.assert_array_equal(a.range, b.range)
    dev = np.linalg.norm(a.pose_position - b.pose_position, axis=1)
    assert dev[0] == 0.0 and dev.max() > 0.05
    np.testing.assert_array_equal(a.pose_position[:, 2], b.pose_position[:, 2])  # horizontal drift only


def test_route_covers_every_road():
    wp, blocks = campus_layout()
    assert blocks.shape == (12, 4)
    assert wp[:, 0].min() == 0 and wp[:, 0].max() == 600 and wp[:, 1].max() == 450


def test_bad_scenario_and_drift():
    with pytest.raises(ValueError, match="scenario"):
        simulate("harbour")
    with pytest.raises(ValueError, match="drift"):
        simulate("small", drift=-1.0)
