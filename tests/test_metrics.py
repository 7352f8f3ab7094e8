"""Ranging statistics and evaluation: known answers, NumPy references, rigid-motion invariance."""

from __future__ import annotations

import numpy as np
import pytest

from jaxcal import metrics
from jaxcal.data import MeshDataset, Result, TrajectoryDataset, mesh_true_distances
from jaxcal.errors import JaxcalError
from jaxcal.mesh.frame import to_frame


def test_error_statistics_known_answers():
    x = np.arange(101) / 10.0  # 0.0, 0.1, ..., 10.0
    s = metrics.error_statistics(np.concatenate([x, [np.nan]]))
    assert s["count"] == 101
    assert s["mean_m"] == pytest.approx(5.0)
    assert s["median_m"] == pytest.approx(5.0) and s["p50_m"] == pytest.approx(5.0)
    assert s["variance_m2"] == pytest.approx((101**2 - 1) / 12 * 0.01)  # discrete uniform
    assert s["p25_m"] == pytest.approx(2.5) and s["p75_m"] == pytest.approx(7.5)
    # linear interpolation: quantile q of 0..100 (step 0.1) is 10 q
    assert s["q1sigma_m"] == pytest.approx(6.827)
    assert s["q2sigma_m"] == pytest.approx(9.545)
    assert s["q3sigma_m"] == pytest.approx(9.973)
    empty = metrics.error_statistics(np.array([np.nan]))
    assert empty["count"] == 0 and np.isnan(empty["mean_m"])


def _mesh(range_, truth, los=None, **kw):
    k = range_.shape[0]
    n = truth.shape[0]
    return MeshDataset(
        name="m",
        node_ids=[f"n{i}" for i in range(n)],
        time=np.arange(k, dtype=float),
        range=range_,
        truth=truth,
        los=los,
        **kw,
    )


def test_ranging_statistics_groups_against_numpy():
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 20, (5, 2))
    d = mesh_true_distances(truth)
    k = 30
    err = rng.normal(0.3, 1.0, (k, 5, 5))  # asymmetric: i->j and j->i independent measurements
    r = (d[None] + np.abs(err)).astype(np.float32)
    r[:, np.arange(5), np.arange(5)] = np.nan
    r[rng.random(r.shape) < 0.2] = np.nan
    los = np.ones((5, 5), np.int8)
    los[0, 3] = los[3, 0] = los[1, 4] = 0
    ds = _mesh(r, truth, los)
    st = metrics.ranging_statistics(ds)
    a = np.abs(r.astype(np.float64) - d[None])
    off = ~np.eye(5, dtype=bool)[None] & np.isfinite(a)
    is_los = np.broadcast_to(los == 1, a.shape)
    for name, mask in (("los", off & is_los), ("nlos", off & ~is_los), ("all", off)):
        want = a[mask]
        g = st[name]
        assert g["count"] == want.size
        assert g["share"] == pytest.approx(want.size / off.sum())
        assert g["mean_m"] == pytest.approx(want.mean())
        assert g["variance_m2"] == pytest.approx(want.var())
        assert g["q2sigma_m"] == pytest.approx(np.quantile(want, 0.9545))
        assert g["p75_m"] == pytest.approx(np.quantile(want, 0.75))


def test_symmetric_matrices_count_each_measurement_once():
    truth = np.array([[0.0, 0.0], [3.0, 4.0], [6.0, 0.0]])
    r = np.full((2, 3, 3), np.nan, np.float32)
    r[:, 0, 1] = r[:, 1, 0] = [5.5, 6.0]  # one measurement per epoch, stored both ways
    r[:, 0, 2] = [6.5, 7.0]  # one direction only
    r[:, 2, 0] = [6.0, 8.0]  # the other direction measured separately
    st = metrics.ranging_statistics(_mesh(r, truth))
    assert st["all"]["count"] == 6
    assert st["all"]["mean_m"] == pytest.approx(np.mean([0.5, 1.0, 0.5, 1.0, 0.0, 2.0]))
    assert np.isnan(st["los"]["share"])  # no LOS labels


def test_pairwise_rmse_and_qq_against_loops():
    rng = np.random.default_rng(4)
    truth = rng.uniform(0, 10, (4, 3))
    d = mesh_true_distances(truth)
    r = (d[None] + rng.normal(0, 0.3, (20, 4, 4))).astype(np.float32)
    r[:, np.arange(4), np.arange(4)] = np.nan
    r[:, 1, 2] = np.nan
    r[:5, 0, 3] = np.nan
    ds = _mesh(r, truth)
    pr = metrics.pairwise_rmse(ds)
    for i in range(4):
        for j in range(4):
            e = r[:, i, j].astype(np.float64) - d[i, j]
            e = e[np.isfinite(e)]
            if e.size == 0:
                assert np.isnan(pr[i, j])
            else:
                assert pr[i, j] == pytest.approx(np.sqrt(np.mean(e**2)))
    exact = r.copy()
    exact[np.isfinite(exact)] = np.broadcast_to(d, r.shape)[np.isfinite(exact)]
    q = metrics.qq_r2(_mesh(exact, truth))
    assert q["r2"] == pytest.approx(1.0) and q["r2_qq"] == pytest.approx(1.0)
    noisy = metrics.qq_r2(ds)
    assert 0.5 < noisy["r2"] < 1.0


def _result(pos, track=None, frame="anchors:0,1,2", ids=None):
    n = pos.shape[0]
    return Result(
        ids=ids or [f"n{i}" for i in range(n)],
        position=pos,
        method="x",
        dataset="m",
        frame=frame,
        track_time=None if track is None else np.arange(track.shape[0], dtype=float),
        track_position=track,
    )


def _scene():
    truth = np.array([[2.0, 1.0, 1.6], [12.0, 3.0, 1.6], [5.0, 9.0, 1.6], [14.0, 11.0, 1.6], [8.0, 4.0, 1.6]])
    return truth


def test_evaluate_mesh_known_errors_and_availability():
    truth = _scene()
    tf = to_frame(truth, 0, 1, 2)[:, :2]
    k = 10
    track = np.repeat(tf[None], k, axis=0)
    track[:, 3] += [0.3, 0.4]  # node 3 off by 0.5 m at every epoch
    track[:4, 4] = np.nan  # node 4 available 60 %
    track[4:, 4] += [1.0, 0.0]
    pos = tf.copy()
    pos[3] += [0.0, 2.0]
    ds = _mesh(np.full((k, 5, 5), np.nan), truth)
    ev = metrics.evaluate(_result(pos, track), ds)
    nodes = {n["id"]: n for n in ev["nodes"]}
    assert nodes["n3"]["rmse_m"] == pytest.approx(0.5)
    assert nodes["n3"]["final_error_m"] == pytest.approx(2.0)
    assert nodes["n4"]["availability"] == pytest.approx(0.6) and nodes["n3"]["availability"] == 1.0
    assert nodes["n4"]["rmse_m"] == pytest.approx(1.0)
    # rmse over (node, epoch) estimates except a0: nodes 1, 2 exact (20 zeros), node 3 (10 x 0.25), node 4 (6 x 1)
    assert ev["rmse_m"] == pytest.approx(np.sqrt((10 * 0.25 + 6 * 1.0) / (30 + 6)))
    assert ev["final_rmse_m"] == pytest.approx(np.sqrt(4.0 / 4))
    x, p = ev["ecdf"]["epoch_error"]
    assert x.size == 36 and p[-1] == 1.0 and np.all(np.diff(x) >= 0)
    # no track: errors of the final positions
    ev2 = metrics.evaluate(_result(pos), ds)
    assert ev2["rmse_m"] == pytest.approx(ev2["final_rmse_m"])


@pytest.mark.parametrize("reflect", [False, True])
def test_evaluation_invariant_under_rigid_motion_of_truth(reflect):
    rng = np.random.default_rng(8)
    truth = _scene()
    est = to_frame(truth, 2, 4, 0)[:, :2] + rng.normal(0, 0.4, (5, 2))
    track = to_frame(truth, 2, 4, 0)[None, :, :2] + rng.normal(0, 0.4, (6, 5, 2))
    res = _result(est, track, frame="anchors:2,4,0")
    ds = _mesh(np.full((1, 5, 5), np.nan), truth)
    base = metrics.evaluate(res, ds)
    ang = rng.uniform(0, 2 * np.pi)
    rz = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    if reflect:
        rz = rz @ np.diag([1.0, -1.0, 1.0])
    moved = truth @ rz.T + np.array([100.0, -40.0, 0.0])
    for truth2 in (moved, moved[:, :2]):
        ev = metrics.evaluate(res, _mesh(np.full((1, 5, 5), np.nan), truth2))
        for key in ("rmse_m", "final_rmse_m", "aligned_rmse_m"):
            assert ev[key] == pytest.approx(base[key], abs=1e-9)
        for a, b in zip(ev["nodes"], base["nodes"], strict=True):
            assert a["rmse_m"] == pytest.approx(b["rmse_m"], abs=1e-9)
    assert base["aligned_rmse_m"] <= base["final_rmse_m"] + 1e-12


def test_2d_estimate_against_3d_truth_uses_first_two_axes_after_3d_transform():
    truth = _scene()
    truth[3, 2] = 4.0  # one node higher: its 3-D frame coordinates have z != 0
    t3 = to_frame(truth, 0, 1, 2)
    ev = metrics.evaluate(_result(t3[:, :2]), _mesh(np.full((1, 5, 5), np.nan), truth))
    assert ev["final_rmse_m"] == pytest.approx(0.0, abs=1e-12)
    assert ev["aligned_rmse_m"] == pytest.approx(0.0, abs=1e-9)


def test_evaluate_errors_are_one_line():
    ds = _mesh(np.full((1, 3, 3), np.nan), np.array([[0.0, 0], [1, 0], [0, 1]]))
    with pytest.raises(JaxcalError, match="not in the truth"):
        metrics.evaluate(_result(np.zeros((3, 2)), ids=["a", "b", "c"]), ds)
    no_truth = _mesh(np.full((1, 3, 3), np.nan), np.full((3, 2), np.nan))
    with pytest.raises(JaxcalError, match="no truth"):
        metrics.evaluate(_result(np.zeros((3, 2))), no_truth)


def test_evaluate_trajectory_per_anchor():
    at = np.array([[0.0, 0, 0], [10, 0, 2], [0, 10, 1]])
    ds = TrajectoryDataset(
        name="tr",
        anchor_ids=["A", "B", "C"],
        tag_ids=["T"],
        lever_arm=np.zeros((1, 3)),
        pose_time=np.arange(3.0),
        pose_position=np.zeros((3, 3)),
        range_time=[0.5],
        range_anchor=[0],
        range_tag=[0],
        range=[1.0],
        anchor_truth=at,
    )
    est = at[[2, 0, 1]] + np.array([[0, 0, 0.5], [3, 4, 0], [np.nan] * 3])
    res = Result(ids=["C", "A", "B"], position=est, method="gp", dataset="tr", frame="world")
    ev = metrics.evaluate(res, ds)
    errs = {a["id"]: a["error_m"] for a in ev["anchors"]}
    assert errs["C"] == pytest.approx(0.5) and errs["A"] == pytest.approx(5.0) and np.isnan(errs["B"])
    assert ev["mean_error_m"] == pytest.approx(2.75)


def test_trajectory_ranging_errors_with_lever_arm_and_rotation():
    # body rotated 90 degrees about z: lever (1, 0, 0) points along world y
    q = np.array([0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    ds = TrajectoryDataset(
        name="tr",
        anchor_ids=["A"],
        tag_ids=["T"],
        lever_arm=[[1.0, 0, 0]],
        pose_time=[0.0, 2.0],
        pose_position=[[0.0, 0, 0], [2.0, 0, 0]],
        pose_orientation=[q, q],
        range_time=[1.0],
        range_anchor=[0],
        range_tag=[0],
        range=[5.5],
        range_los=[1],
        anchor_truth=[[1.0, 5.0, 0.0]],
    )
    err, los = metrics.ranging_errors(ds)
    assert err == pytest.approx([1.5])  # tag at (1, 1, 0), anchor 4 m away
    assert list(los) == [1]


def test_covariance_consistency_known_answers():
    truth = _scene()
    tf = to_frame(truth, 0, 1, 2)[:, :2]
    err = np.array([[0.0, 0.0], [0.3, 0.0], [0.1, -0.2], [0.4, 0.3], [0.0, 0.5]])
    cov = np.zeros((5, 2, 2))
    cov[1] = np.diag([0.09, 0.0])  # a1: y fixed by the frame
    cov[2] = np.diag([0.01, 0.04])
    cov[3] = [[0.25, 0.1], [0.1, 0.25]]
    cov[4] = np.diag([0.5, 0.25])
    res = Result(
        ids=[f"n{i}" for i in range(5)],
        position=tf + err,
        method="x",
        dataset="m",
        frame="anchors:0,1,2",
        covariance=cov,
    )
    ds = _mesh(np.full((2, 5, 5), np.nan), truth)
    cc = metrics.covariance_consistency(res, ds)
    nees = 0.09 / 0.09 + 0.01 / 0.01 + 0.04 / 0.04 + err[3] @ np.linalg.inv(cov[3]) @ err[3] + 0.25 / 0.25
    assert cc["nodes"] == 4
    assert cc["nees_per_dof"] == pytest.approx(nees / 7)
    assert cc["error_rmse_m"] == pytest.approx(np.sqrt(np.mean([0.09, 0.05, 0.25, 0.25])))
    assert cc["predicted_rmse_m"] == pytest.approx(np.sqrt(np.mean([0.09, 0.05, 0.5, 0.75])))
    # inside the 95 % ellipse: NEES 1 (1 dof, < 3.84), 2, 0.8 (2 dof, < 5.99), 1: all four
    assert cc["coverage95"] == 1.0 and "h_nees_per_dof" not in cc
    assert metrics.covariance_consistency(_result(tf), ds) is None  # no covariance


def test_covariance_consistency_trajectory_horizontal_vertical_and_nan_axis():
    from jaxcal.data import TrajectoryDataset

    truth = np.array([[0.0, 0, 3], [10, 0, 4], [0, 10, 5]])
    ds = TrajectoryDataset(
        name="t",
        anchor_ids=["a", "b", "c"],
        tag_ids=["t"],
        lever_arm=[[0, 0, 0]],
        pose_time=[0.0, 1.0],
        pose_position=np.zeros((2, 3)),
        range_time=[0.5],
        range_anchor=[0],
        range_tag=[0],
        range=[1.0],
        anchor_truth=truth,
    )
    err = np.array([[0.1, 0.0, 0.3], [0.0, 0.2, -0.1], [0.0, 0.0, np.nan]])
    cov = np.repeat(np.diag([0.01, 0.01, 0.01])[None], 3, axis=0)
    res = Result(ids=["a", "b", "c"], position=truth + err, method="nls", dataset="t", frame="world", covariance=cov)
    cc = metrics.covariance_consistency(res, ds)
    assert cc["nodes"] == 3
    assert cc["h_nees_per_dof"] == pytest.approx((1 + 4 + 0) / 6)
    assert cc["v_nees_per_dof"] == pytest.approx((9 + 1) / 2)  # the NaN height is left out
    assert cc["nees_per_dof"] == pytest.approx((1 + 9 + 4 + 1 + 0) / 8)
    # chi2(3) 95 % = 7.81: a (NEES 10) outside, b (5) inside; c: 2 dof, NEES 0: inside
    assert cc["coverage95"] == pytest.approx(2 / 3)
    # apart: horizontal NEES 1, 4, 0 all inside chi2(2) 95 % = 5.99; vertical 9 (outside 3.84) and 1
    assert cc["h_coverage95"] == 1.0 and cc["v_coverage95"] == pytest.approx(0.5)
    assert cc["v_error_rmse_m"] == pytest.approx(np.sqrt((0.09 + 0.01) / 2))


def test_covariance_consistency_3d_takes_the_nearer_mirror_image():
    rng = np.random.default_rng(3)
    truth = _scene() + np.c_[np.zeros((5, 2)), [0.0, 0.0, 0.0, 2.0, -1.5]]
    tf = to_frame(truth, 0, 1, 2)
    est = tf * np.array([1.0, 1.0, -1.0]) + rng.normal(0, 0.05, tf.shape)  # the mirror-image solution
    cov = np.repeat(np.eye(3)[None] * 0.05**2, 5, axis=0)
    res = Result(
        ids=[f"n{i}" for i in range(5)], position=est, method="x", dataset="m", frame="anchors:0,1,2", covariance=cov
    )
    cc = metrics.covariance_consistency(res, _mesh(np.full((2, 5, 5), np.nan), truth))
    assert cc["error_rmse_m"] < 0.2 and cc["nees_per_dof"] < 5
