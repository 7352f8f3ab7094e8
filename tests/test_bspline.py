"""Cumulative B-spline pose interpolation, lever arms and orientation interpolation."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.data import TrajectoryDataset
from jaxcal.trajectory import bspline, poses


def test_cubic_blending_matrix_is_the_textbook_one():
    m = bspline.blending_matrix(4) * 6.0
    ref = np.array([[1, -3, 3, -1], [4, 0, -6, 3], [1, 3, 3, -3], [0, 0, 0, 1]], dtype=float)
    np.testing.assert_allclose(m, ref, atol=1e-12)
    for k in (2, 3, 4, 5):  # partition of unity: the weights sum to 1 for every u
        np.testing.assert_allclose(bspline.blending_matrix(k).sum(axis=0), np.eye(k)[0], atol=1e-12)
        np.testing.assert_allclose(bspline.cumulative_blending_matrix(k)[0], np.eye(k)[0], atol=1e-12)


@pytest.mark.parametrize("order", [2, 3, 4, 5])
def test_reproduces_polynomials_of_its_degree(order):
    rng = np.random.default_rng(order)
    t = np.unique(np.sort(rng.uniform(0.0, 10.0, 300)))  # irregular sampling
    coef = rng.normal(size=(order, 3))
    poly = lambda s: np.stack([np.polyval(coef[:, d], s) for d in range(3)], axis=1)  # noqa: E731
    sp = bspline.fit_pieces(t, poly(t), order=order, knot_dt_s=0.37)
    tq = np.linspace(t[0], t[-1], 400)
    got = np.asarray(bspline.evaluate(sp, jnp.asarray(tq)))
    ref = poly(tq)
    # exact up to round-off of the normal equations (relative to the polynomial's size)
    assert np.abs(got - ref).max() < 1e-7 * np.abs(ref).max()


def test_gaps_split_the_stream_and_evaluate_to_nan():
    t = np.concatenate([np.arange(0.0, 5.0, 0.1), np.arange(20.0, 25.0, 0.1)])
    sp = bspline.fit_pieces(t, np.sin(t)[:, None])
    assert sp.t0.shape == (2,)
    v = np.asarray(bspline.evaluate(sp, jnp.array([1.03, 10.0, 21.05, 30.0])))[:, 0]
    assert np.isnan(v[1]) and np.isnan(v[3])
    np.testing.assert_allclose(v[[0, 2]], np.sin([1.03, 21.05]), atol=1e-4)


def test_quaternion_rotation_and_slerp():
    yaw = np.pi / 2
    q = jnp.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])
    np.testing.assert_allclose(poses.quat_rotate(q, jnp.array([1.0, 0.0, 0.0])), [0.0, 1.0, 0.0], atol=1e-12)
    qs = jnp.array([[0.0, 0.0, 0.0, 1.0], q])
    mid = poses.slerp_orientation(jnp.array([0.0, 1.0]), qs, jnp.array([0.5]))[0]
    np.testing.assert_allclose(mid, [0.0, 0.0, np.sin(yaw / 4), np.cos(yaw / 4)], atol=1e-12)


def test_tag_positions_apply_lever_arm_and_hold_static_dwells():
    # Two dwells (two poses each, same position), as the HYMN importer writes them, then rotation.
    t = np.array([0.0, 10.0, 20.0, 30.0])
    pos = np.array([[0.0, 0, 0], [0, 0, 0], [5, 1, 0], [5, 1, 0]])
    yaw = np.pi / 2
    quat = np.tile([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)], (4, 1))
    ds = TrajectoryDataset(
        name="d",
        anchor_ids=["a"],
        tag_ids=["t"],
        lever_arm=[[1.0, 0.0, 0.5]],
        pose_time=t,
        pose_position=pos,
        pose_orientation=quat,
        range_time=[2.0, 25.0, 31.0],
        range_anchor=[0, 0, 0],
        range_tag=[0, 0, 0],
        range=[1.0, 1.0, 1.0],
    )
    groups, info = poses.prepare(ds, max_gap_s=100.0)
    got = np.asarray(groups.position[0])[np.asarray(groups.mask[0])]
    np.testing.assert_allclose(got, [[0.0, 1.0, 0.5], [5.0, 2.0, 0.5]], atol=1e-12)
    assert info["ranges_dropped"] == 1  # t = 31 s lies after the last pose
