"""Reports and figures: `jaxcal report` end to end on a small simulated scenario and a tiny real
`jaxcal sweep`, sweep surfaces against a brute-force reference, bad input, and the plotting
functions (labelled axes, colour bars, ellipse geometry against a direct computation).

Kept lean: one PGP compilation for the calibration and one for the posterior re-runs (the auto and
the explicit posterior spec share the scan length and snapshot count), one tiny sweep.
"""

from __future__ import annotations

import json
import re

import h5py
import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli
from jaxcal import plot
from jaxcal.data import Result, TrajectoryDataset
from jaxcal.errors import JaxcalError
from jaxcal.io import hdf5
from jaxcal.methods import calibrate
from jaxcal.metrics import evaluate, qq_r2, ranging_statistics
from jaxcal.report import PosteriorSpec, parse_posteriors, sweep_surfaces, write_report
from jaxcal.sim.mesh import simulate

PNG = b"\x89PNG\r\n\x1a\n"
N_EPOCHS = 12  # auto posterior epochs: 3 and 10 (AUTO_POSTERIOR_EPOCHS below 12)
PGP = {"likelihood": "dense"}

# a tiny real sweep: 2 x 2 grid x 2 seeds of the small scenario, 8 epochs on 2 m cells
SWEEP_SPEC = """
method = "pgp"
epochs = 8
batch_size = 4
[params]
cell_m = 2.0
max_hyp = 4
top_k = 8
min_refs = 2
likelihood = "dense"
[grid]
sigma_r = [0.3, 1.0]
tau = [0.5, 0.9]
[[scenarios]]
simulate = "small"
config = "conf1"
seeds = [0, 1]
"""


@pytest.fixture(scope="module")
def mesh_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("mesh")
    ds = simulate("small", seed=3, n_epochs=N_EPOCHS)
    hdf5.write(d / "ds.h5", ds)
    results = {}
    for m in ("cf", "pgp"):
        # the dense likelihood compiles in half the time of the default's two branches; the report
        # re-runs PGP with the result's own parameters, so its posterior re-run gains as well
        results[m] = calibrate(ds, m, params=PGP if m == "pgp" else None, config="conf1")
        hdf5.write(d / f"{m}.h5", results[m])
    return d, ds, results


@pytest.fixture(scope="module")
def sweep_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("sweep")
    (d / "spec.toml").write_text(SWEEP_SPEC)
    proc = run_cli("sweep", d / "spec.toml", "-o", d / "sweep.h5", "--quiet")
    assert proc.returncode == 0, proc.stderr
    return d / "sweep.h5"


def _reference_surface(path, metric="rmse_m"):
    """Mean over seeds of every (sigma_r, tau) cell, by a plain loop over the file's runs."""
    with h5py.File(path, "r") as f:
        s, t = f["runs/param_sigma_r"][()], f["runs/param_tau"][()]
        v, done = f[f"metrics/{metric}"][()], f["done"][()]
    assert done.all()
    sv, tv = sorted(set(s)), sorted(set(t))
    ref = np.zeros((len(sv), len(tv)))
    for i, a in enumerate(sv):
        for j, b in enumerate(tv):
            ref[i, j] = np.mean([v[r] for r in range(len(v)) if s[r] == a and t[r] == b])
    return np.array(sv), np.array(tv), ref


def _check_pngs(out, names):
    for name in names:
        data = (out / name).read_bytes()
        assert data[:8] == PNG and len(data) > 5000, name


def test_report_cli_mesh_and_sweep(mesh_files, sweep_file):
    d, ds, results = mesh_files
    out = d / "report"
    proc = run_cli(
        "report",
        d / "cf.h5",
        sweep_file,  # results and sweep files mixed: told apart by layout
        d / "pgp.h5",
        "--truth",
        d / "ds.h5",
        "-o",
        out,
        "--posteriors",
        "none",  # the posterior re-run is tested in process (one compilation less)
        "--json",
    )
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
        "sweep_0.png",
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
    assert "posteriors" not in summary
    sv, tv, ref = _reference_surface(sweep_file)
    (sw,) = summary["sweeps"]
    assert sw["sigma_r_m"] == list(sv) and sw["tau"] == list(tv) and sw["seeds"] == [0, 1]
    np.testing.assert_allclose(sw["values"], ref, rtol=1e-12)
    assert sw["n_runs"] == [[2, 2], [2, 2]] and sw["n_failed"] == [[0, 0], [0, 0]]
    for v in ref.ravel():
        assert f"{v:,.3f}" in page


def test_report_cli_sweep_only(sweep_file, tmp_path):
    # no truth needed; another metric; an unknown metric is refused by argparse
    proc = run_cli("report", sweep_file, "-o", tmp_path / "r", "--sweep-metric", "final_rmse_m", "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["figures"] == ["sweep_0.png"] and summary["dataset"] is None
    sv, tv, ref = _reference_surface(sweep_file, "final_rmse_m")
    (sw,) = summary["sweeps"]
    assert sw["metric"] == "final_rmse_m" and sw["title"] == "pgp: small/conf1, mean of 2 seeds"
    np.testing.assert_allclose(sw["values"], ref, rtol=1e-12)
    i, j = np.unravel_index(np.argmin(ref), ref.shape)
    assert sw["best"] == {
        "sigma_r_m": sv[i],
        "tau": tv[j],
        "final_rmse_m": pytest.approx(ref[i, j]),
    }
    _check_pngs(tmp_path / "r", ["sweep_0.png"])
    page = (tmp_path / "r" / "index.html").read_text()
    assert "final RMSE [m]" in page and f"{ref[i, j]:,.3f}" in page


def test_report_posteriors_auto_spec_and_labels(mesh_files, tmp_path):
    d, ds, results = mesh_files
    write_report([results["cf"], results["pgp"]], ds, tmp_path / "auto")
    numbers = json.loads((tmp_path / "auto" / "report.json").read_text())
    assert numbers["posteriors"]["epochs"] == [3, 10]  # AUTO_POSTERIOR_EPOCHS below N_EPOCHS
    assert numbers["posteriors"]["result"] == "pgp/conf1"
    a2 = results["pgp"].ids[results["pgp"].frame_anchors()[2]]
    assert numbers["posteriors"]["nodes"][0] == a2  # a2, then the best and worst other nodes
    assert "fig06_posteriors_pgp_conf1.png" in numbers["figures"]
    _check_pngs(tmp_path / "auto", ["fig06_posteriors_pgp_conf1.png"])
    spec = parse_posteriors("N3,N4@1,10")  # same scan length and snapshot count: no recompilation
    assert spec == PosteriorSpec(("N3", "N4"), (1, 10))
    index = write_report([results["pgp"]], ds, tmp_path, labels=["mine"], posteriors=spec)
    numbers = json.loads((tmp_path / "report.json").read_text())
    assert numbers["posteriors"] == {"result": "mine", "nodes": ["N3", "N4"], "epochs": [1, 10]}
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
    proc = run_cli("report", d / "cf.h5", "-o", tmp_path / "r")
    assert_one_line_error(proc, "need --truth")


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
    index = write_report([res], ds, tmp_path, sweeps=[{"sigma_r": s, "tau": t, "rmse": rmse, "title": "toy"}])
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


# ------------------------------------------------------------------------------- sweep surfaces
def _synthetic_sweep():
    """Two scenarios, sigma_r x tau x sigma_v x 3 seeds; some runs failed (NaN), some not done."""
    rng = np.random.default_rng(7)
    rows = [
        (sc, seed, s, t, v)
        for sc in ("a", "b")
        for seed in (0, 1, 2)
        for s in (0.2, 0.5, 1.0)
        for t in (0.5, 0.9)
        for v in (0.3, 1.0)
    ]
    sc, seed, s, t, v = (np.array(c) for c in zip(*rows, strict=True))
    value = rng.uniform(0.5, 3.0, len(rows))
    value[(sc == "a") & (s == 0.2) & (t == 0.5) & (seed == 1)] = np.nan  # failed runs
    value[(sc == "b") & (s == 1.0) & (t == 0.9) & (v == 0.3)] = np.nan  # every seed failed
    done = np.ones(len(rows), bool)
    done[(sc == "b") & (s == 0.5) & (seed == 2)] = False
    runs = {
        "scenario": sc,
        "config": np.full(len(rows), "conf1"),
        "seed": seed,
        "param_sigma_r": s,
        "param_tau": t,
        "param_sigma_v": v,
    }
    return runs, {"rmse_m": value, "nlpl": -value}, done


def _brute(runs, value, done, scen, s, t, v):
    """Mean of the finite, done runs of one (scenario, sigma_r, tau, sigma_v) cell."""
    x = [
        value[r]
        for r in range(len(value))
        if runs["scenario"][r] == scen
        and runs["param_sigma_r"][r] == s
        and runs["param_tau"][r] == t
        and runs["param_sigma_v"][r] == v
        and done[r]
        and np.isfinite(value[r])
    ]
    return np.mean(x) if x else np.nan


def test_sweep_surfaces_best_and_facet_match_brute_force(tmp_path):
    runs, metrics, done = _synthetic_sweep()
    value = np.where(done, metrics["rmse_m"], np.nan)
    best = sweep_surfaces(runs, metrics, done, method="pgp")
    assert [b["scenario"] for b in best] == ["a", "b"]
    for b in best:
        assert list(b["sigma_r"]) == [0.2, 0.5, 1.0] and list(b["tau"]) == [0.5, 0.9]
        for i, s in enumerate(b["sigma_r"]):
            for j, t in enumerate(b["tau"]):
                cands = {v: _brute(runs, value, done, b["scenario"], s, t, v) for v in (0.3, 1.0)}
                fin = {v: x for v, x in cands.items() if np.isfinite(x)}
                assert b["rmse"][i, j] == pytest.approx(min(fin.values()))
                assert b["best_others"]["sigma_v"][i, j] == min(fin, key=fin.get)
    b = best[1]
    assert b["n_runs"][1, 0] == 6 and b["n_done"][1, 0] == 4  # seed 2 of sigma_r 0.5 not done
    assert b["n_failed"][2, 1] == 3 and best[0]["n_failed"][0, 0] == 2
    facet = sweep_surfaces(runs, metrics, done, others="facet")
    assert [(f["scenario"], f["facet"]) for f in facet] == [
        (sc, {"sigma_v": v}) for sc in ("a", "b") for v in (0.3, 1.0)
    ]
    for f in facet:
        ref = [
            [_brute(runs, value, done, f["scenario"], s, t, f["facet"]["sigma_v"]) for t in f["tau"]]
            for s in f["sigma_r"]
        ]
        np.testing.assert_allclose(f["rmse"], ref)  # NaN where every seed failed
    assert np.isnan(facet[2]["rmse"][2, 1]) and "sigma_v 0.3" in facet[2]["title"]
    # the report shows the chosen sigma_v per cell and the failures
    index = write_report([], None, tmp_path, sweeps=best)
    page = index.read_text()
    assert "sigma_v" in page and "failed" in page and "done]" in page


def test_sweep_surfaces_unswept_axis_and_errors(tmp_path):
    runs, metrics, done = _synthetic_sweep()
    del runs["param_tau"]
    with pytest.raises(JaxcalError, match="tau is neither swept"):
        sweep_surfaces(runs, metrics, done)
    (one, _) = sweep_surfaces(runs, metrics, done, fixed={"tau": 0.8}, metric="nlpl")
    assert list(one["tau"]) == [0.8] and one["rmse"].shape == (3, 1)
    assert one["label"].startswith("NLPL")
    del runs["param_sigma_r"]
    with pytest.raises(JaxcalError, match="neither sigma_r nor tau"):
        sweep_surfaces(runs, metrics, done)
    with pytest.raises(JaxcalError, match="sweep metric"):
        sweep_surfaces(runs, metrics, done, metric="bogus")
    res = Result(ids=["a"], position=np.zeros((1, 3)), method="nls", dataset="x", frame="world")
    with pytest.raises(JaxcalError, match="truth"):
        write_report([res], None, tmp_path)


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
        "matrix": plot.pairwise_rmse_matrix(np.where(np.eye(4) > 0, np.nan, rng.random((4, 4)) * 5 + 0.1), ids),
        "post": plot.posterior_grids(
            np.arange(-5.0, 5.0, 0.5),
            rng.dirichlet(np.ones(400), (2, 3)).reshape(2, 3, 20, 20),
            ids[:3],
            [1, 4],
            rng.random((3, 2)),
            np.zeros((2, 3, 2)),
        ),
        "sweep": plot.sweep_surface(np.array([0.1, 0.2]), np.array([0.5, 0.9, 0.95]), rng.random((2, 3))),
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
    assert a == pytest.approx(np.sqrt(5.991464547 * 4.0)) and b == pytest.approx(np.sqrt(5.991464547))
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
