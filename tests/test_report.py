"""Reports and figures: `jaxcal report` end to end on a small simulated scenario, bad input, and the
plotting functions (labelled axes, colour bars, ellipse geometry against a direct computation)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli
from jaxcal import plot
from jaxcal.data import Result, TrajectoryDataset
from jaxcal.errors import JaxcalError
from jaxcal.io import hdf5
from jaxcal.methods import calibrate
from jaxcal.metrics import evaluate, qq_r2, ranging_statistics
from jaxcal.report import PosteriorSpec, parse_posteriors, write_report
from jaxcal.sim.mesh import simulate

PNG = b"\x89PNG\r\n\x1a\n"
N_EPOCHS = 40


@pytest.fixture(scope="module")
def mesh_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("mesh")
    ds = simulate("small", seed=3, n_epochs=N_EPOCHS)
    hdf5.write(d / "ds.h5", ds)
    results = {}
    for m in ("cf", "pgp"):
        results[m] = calibrate(ds, m, config="conf1")
        hdf5.write(d / f"{m}.h5", results[m])
    return d, ds, results


def _check_pngs(out, names):
    for name in names:
        data = (out / name).read_bytes()
        assert data[:8] == PNG and len(data) > 5000, name


def test_report_cli_mesh(mesh_files):
    d, ds, results = mesh_files
    out = d / "report"
    proc = run_cli("report", d / "cf.h5", d / "pgp.h5", "--truth", d / "ds.h5", "-o", out, "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    expected = {
        "fig09_ranging_residuals.png",
        "fig11a_qq.png",
        "fig11b_pairwise_rmse.png",
        "fig10_availability.png",
        "fig12a_node_errors_cf.png",
        "fig12a_node_errors_pgp.png",
        "fig12b_ecdf_node_rmse.png",
        "fig13b_ecdf_epoch_errors.png",
        "positions_conf1.png",
        "fig06_posteriors_pgp_conf1.png",
    }
    pngs = {p.name for p in out.glob("*.png")}
    assert pngs == expected
    assert set(summary["figures"]) == expected
    _check_pngs(out, pngs)
    page = (out / "index.html").read_text()
    referenced = set(re.findall(r'<img src="([^"]+)"', page))
    assert referenced == pngs
    # the key numbers are on the page, as computed by the metrics module
    stats = ranging_statistics(ds)
    for g in ("los", "nlos", "all"):
        assert f"{stats[g]['mean_m']:,.2f}" in page
        assert f"{stats[g]['q1sigma_m']:,.2f}" in page
    assert f"{qq_r2(ds)['r2_qq']:.4f}" in page
    for m, label in (("cf", "cf/conf1"), ("pgp", "pgp/conf1")):
        ev = evaluate(results[m], ds)
        assert label in page
        assert f"{ev['rmse_m']:,.2f}" in page
        assert summary["groups"][label]["rmse_m"] == pytest.approx(ev["rmse_m"])
    assert summary["posteriors"]["epochs"] == [3, 10, 30]  # auto: AUTO_POSTERIOR_EPOCHS below 40


def test_report_posterior_spec_and_labels(mesh_files, tmp_path):
    d, ds, results = mesh_files
    spec = parse_posteriors("N3,N4@1,5")
    assert spec == PosteriorSpec(("N3", "N4"), (1, 5))
    index = write_report([results["pgp"]], ds, tmp_path, labels=["mine"], posteriors=spec)
    numbers = json.loads((tmp_path / "report.json").read_text())
    assert numbers["posteriors"] == {"result": "mine", "nodes": ["N3", "N4"], "epochs": [1, 5]}
    assert "mine" in index.read_text()
    with pytest.raises(JaxcalError, match="unknown node"):
        write_report([results["pgp"]], ds, tmp_path, posteriors=PosteriorSpec(("ZZ",), (1,)))
    with pytest.raises(JaxcalError, match="beyond"):
        write_report([results["pgp"]], ds, tmp_path, posteriors=PosteriorSpec(("N3",), (N_EPOCHS,)))


@pytest.mark.parametrize("text", ["N3@", "@1,2", "N3@x", "N3@-1", "N3"])
def test_parse_posteriors_rejects(text):
    with pytest.raises(JaxcalError, match="--posteriors"):
        parse_posteriors(text)


def test_report_bad_input_one_line(mesh_files, tmp_path):
    d, _, _ = mesh_files
    proc = run_cli("report", d / "cf.h5", "--truth", d / "pgp.h5", "-o", tmp_path / "r")
    assert_one_line_error(proc, "expected mesh or trajectory")
    proc = run_cli("report", d / "ds.h5", "--truth", d / "ds.h5", "-o", tmp_path / "r")
    assert_one_line_error(proc, "expected result")
    proc = run_cli("report", tmp_path / "missing.h5", "--truth", d / "ds.h5", "-o", tmp_path / "r")
    assert_one_line_error(proc, "missing.h5")


def test_report_mismatched_kind(mesh_files, tmp_path):
    _, ds, results = mesh_files
    traj = _trajectory()
    with pytest.raises(JaxcalError, match="does not fit"):
        write_report([results["cf"]], traj, tmp_path)
    with pytest.raises(JaxcalError, match="labels"):
        write_report([results["cf"]], ds, tmp_path, labels=["a", "b"], posteriors="none")


def _trajectory():
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 60.0, 121)
    path = np.column_stack([10 * np.cos(t / 10), 8 * np.sin(t / 10), np.full_like(t, 1.0)])
    anchors = np.array([[0.0, 0.0, 3.0], [12.0, 5.0, 2.5], [-6.0, 9.0, 2.0]])
    rt = np.repeat(t[:-1] + 0.25, 3)
    ra = np.tile(np.arange(3), t.size - 1)
    pos = np.column_stack([np.interp(rt, t, path[:, c]) for c in range(3)])
    r = np.linalg.norm(anchors[ra] - pos, axis=1) + rng.normal(0, 0.1, rt.size)
    los = np.where(ra == 2, 0, 1)
    return TrajectoryDataset(
        name="loop",
        anchor_ids=["A1", "A2", "A3"],
        tag_ids=["T"],
        lever_arm=np.zeros((1, 3)),
        pose_time=t,
        pose_position=path,
        range_time=rt,
        range_anchor=ra,
        range_tag=np.zeros_like(ra),
        range=r,
        range_los=los,
        anchor_truth=anchors,
    )


def test_report_trajectory_and_sweep(tmp_path):
    ds = _trajectory()
    est = ds.anchor_truth + np.array([[0.3, -0.2, 0.1], [0.0, 0.5, 0.0], [1.0, 0.0, -0.5]])
    cov = np.tile(np.diag([0.04, 0.09, 0.25])[None], (3, 1, 1))
    res = Result(
        ids=ds.anchor_ids,
        position=est,
        method="nls",
        dataset=ds.name,
        frame="world",
        covariance=cov,
    )
    s, t = np.array([0.1, 0.2, 0.4]), np.array([0.5, 0.7, 0.9, 0.99])
    rmse = np.add.outer((s - 0.2) ** 2, (t - 0.9) ** 2) + 0.5
    index = write_report(
        [res], ds, tmp_path, sweeps=[{"sigma_r": s, "tau": t, "rmse": rmse, "title": "toy"}]
    )
    pngs = {p.name for p in tmp_path.glob("*.png")}
    assert {
        "anchors_trajectory.png",
        "ecdf_anchor_errors.png",
        "sweep_0.png",
        "fig09_ranging_residuals.png",
        "fig11a_qq.png",
    } == pngs
    _check_pngs(tmp_path, pngs)
    numbers = json.loads((tmp_path / "report.json").read_text())
    assert numbers["sweeps"][0]["best"] == {"sigma_r_m": 0.2, "tau": 0.9, "rmse_m": 0.5}
    ev = evaluate(res, ds)
    assert numbers["groups"]["nls/world"]["mean_error_m"] == pytest.approx(ev["mean_error_m"])
    assert f"{ev['mean_error_m']:.2f}" in index.read_text()
    with pytest.raises(JaxcalError, match="sweep 0"):
        write_report([res], ds, tmp_path / "bad", sweeps=[{"sigma_r": s, "tau": t, "rmse": rmse.T}])


# ------------------------------------------------------------------------------------------ figures
def _labels(fig):
    return [(ax.get_xlabel(), ax.get_ylabel()) for ax in fig.axes if ax.get_label() != "<colorbar>"]


def _has_colorbar(fig):
    return any(ax.get_label() == "<colorbar>" for ax in fig.axes)


def test_figures_have_labelled_axes():
    rng = np.random.default_rng(1)
    ids = ["a", "b", "c", "d"]
    err = rng.normal(0, 0.3, 200)
    los = (rng.random(200) < 0.7).astype(np.int8)
    figs = {
        "hist": plot.ranging_histograms(err, los),
        "qq": plot.qq_plot(np.linspace(1, 10, 11), np.linspace(1.1, 10.5, 11), 0.99, 0.95),
        "avail": plot.availability_bars(ids, {"cf": {"conf1": np.array([1, 0.5, 0.2, 0.0])}}),
        "box": plot.node_error_distributions(ids, {"conf1": np.abs(rng.normal(0, 1, (20, 4)))}),
        "ecdf": plot.rmse_ecdfs({"x": np.abs(rng.normal(0, 1, 30))}),
        "pos": plot.positions_map(
            rng.random((4, 2)) * 10,
            ids,
            {"m": (rng.random((4, 2)) * 10, np.tile(np.eye(2) * 0.1, (4, 1, 1)))},
        ),
        "traj": plot.trajectory_anchors(
            rng.random((50, 3)) * 10,
            rng.random((4, 3)) * 10,
            ids,
            {"m": (rng.random((4, 3)) * 10, np.tile(np.eye(3) * 0.1, (4, 1, 1)))},
        ),
    }
    for name, fig in figs.items():
        for xl, yl in _labels(fig):
            assert xl and yl, name
        assert any("[m]" in xl + yl or "[%]" in yl for xl, yl in _labels(fig)), name
    colour = {
        "matrix": plot.pairwise_rmse_matrix(
            np.where(np.eye(4) > 0, np.nan, rng.random((4, 4)) * 5 + 0.1), ids
        ),
        "post": plot.posterior_grids(
            np.arange(-5.0, 5.0, 0.5),
            rng.dirichlet(np.ones(400), (2, 3)).reshape(2, 3, 20, 20),
            ids[:3],
            [1, 4],
            rng.random((3, 2)),
            np.zeros((2, 3, 2)),
        ),
        "sweep": plot.sweep_surface(
            np.array([0.1, 0.2]), np.array([0.5, 0.9, 0.95]), rng.random((2, 3))
        ),
    }
    for name, fig in colour.items():
        assert _has_colorbar(fig), name
        cbar = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"][0]
        assert "[m]" in cbar.get_ylabel() or "probability" in cbar.get_ylabel(), name
        for xl, yl in _labels(fig):
            assert xl and yl, name
    assert figs["hist"].axes[0].get_yscale() == "log"


def test_covariance_ellipse_matches_eigen_decomposition():
    # axis-aligned: semi-axes sqrt(chi2_2(0.95) * variance), chi2_2(0.95) = -2 ln 0.05 = 5.9915
    a, b, ang = plot.covariance_ellipse(np.diag([4.0, 1.0]), 0.95)
    assert a == pytest.approx(np.sqrt(5.991464547 * 4.0)) and b == pytest.approx(
        np.sqrt(5.991464547)
    )
    assert ang % 180.0 == pytest.approx(0.0, abs=1e-9)
    # rotated by 30 degrees
    th = np.radians(30.0)
    rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    a, b, ang = plot.covariance_ellipse(rot @ np.diag([9.0, 0.25]) @ rot.T, 0.5)
    k2 = -2 * np.log(0.5)
    assert (a, b) == pytest.approx((np.sqrt(k2 * 9.0), np.sqrt(k2 * 0.25)))
    assert ang % 180.0 == pytest.approx(30.0)
    # the 0.95 ellipse holds 95 % of samples (Monte Carlo, 20k draws: +-0.5 % is ~3 sigma)
    cov = np.array([[2.0, 0.8], [0.8, 1.0]])
    x = np.random.default_rng(0).multivariate_normal([0, 0], cov, 20000)
    a, b, ang = plot.covariance_ellipse(cov, 0.95)
    c, s = np.cos(np.radians(ang)), np.sin(np.radians(ang))
    u, v = x @ np.array([c, s]), x @ np.array([-s, c])
    assert np.mean((u / a) ** 2 + (v / b) ** 2 <= 1) == pytest.approx(0.95, abs=0.005)
