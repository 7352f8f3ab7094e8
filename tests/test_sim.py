"""Mesh simulator and channel model (Table I shape, LOS share, determinism) and the CLI around them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli
from jaxcal import metrics
from jaxcal.errors import JaxcalError
from jaxcal.io import hdf5
from jaxcal.sim.channel import ChannelModel, sample_range_errors
from jaxcal.sim.mesh import SCENARIOS, line_of_sight, simulate

# Table I of the grid paper: mean and median of |range error| per class
PAPER = {"los": (0.28, 0.21), "nlos": (3.78, 0.69)}


@pytest.fixture(scope="module")
def torgau():
    return simulate("torgau", seed=0)


def test_torgau_shape_after_the_paper(torgau):
    ds = torgau
    assert ds.n_nodes == 12 and ds.n_epochs == 2000
    np.testing.assert_allclose(np.diff(ds.time), 0.1)
    assert ds.truth.shape == (12, 3) and np.all(ds.truth[:, 2] == ds.truth[0, 2])
    span = ds.truth.max(axis=0) - ds.truth.min(axis=0)
    assert span[0] <= 44 and span[1] <= 30
    iu = np.triu_indices(12, 1)
    assert 0.72 <= ds.los[iu].mean() <= 0.80  # "about 76 % LOS pairs"
    assert dict(ds.configs).keys() == {"conf1", "conf2"}
    st = metrics.ranging_statistics(ds)
    for cls, (mean, median) in PAPER.items():
        assert st[cls]["mean_m"] == pytest.approx(mean, rel=0.3), cls
        assert st[cls]["median_m"] == pytest.approx(median, rel=0.3), cls
    assert st["nlos"]["q2sigma_m"] > 15.0  # the gross outliers of Table I
    assert 0.70 <= st["los"]["share"] <= 0.85


def test_conf2_has_the_d5b4_gap(torgau):
    a0, a1, a2 = torgau.config("conf2")
    d5b4 = torgau.node_ids.index("D5B4")
    assert np.isnan(torgau.range[:, a1, d5b4]).all() and np.isnan(torgau.range[:, d5b4, a1]).all()
    # ... while D5B4 still ranges to several other nodes
    measured = np.isfinite(torgau.range[:, d5b4, :]).mean(axis=0)
    assert (measured > 0.5).sum() >= 6


def test_determinism_and_overrides():
    a = simulate("small", seed=3)
    b = simulate("small", seed=3)
    c = simulate("small", seed=4)
    np.testing.assert_array_equal(a.range, b.range)
    np.testing.assert_array_equal(a.truth, b.truth)
    assert not np.array_equal(np.nan_to_num(a.range), np.nan_to_num(c.range))
    fast = simulate("small", seed=3, n_epochs=7, rate_hz=4.0, symmetric=False, never=((0, 1),))
    assert fast.range.shape == (7, 6, 6)
    np.testing.assert_allclose(fast.time, np.arange(7) / 4.0)
    assert np.isnan(fast.range[:, 0, 1]).all() and np.isnan(fast.range[:, 1, 0]).all()
    assert not np.array_equal(fast.range, np.swapaxes(fast.range, 1, 2))  # independent directions
    sym = simulate("small", seed=3, n_epochs=7)
    np.testing.assert_array_equal(sym.range, np.swapaxes(sym.range, 1, 2))
    with pytest.raises(JaxcalError, match="unknown mesh scenario"):
        simulate("nope")
    with pytest.raises(JaxcalError, match="unknown scenario field"):
        simulate("small", walls_typo=())


def test_line_of_sight_segment_test():
    pts = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [5.0, 5.0]])
    wall = (((5.0, -1.0), (5.0, 1.0)),)  # crosses the 0-1 link only
    los = line_of_sight(pts, wall)
    assert not los[0, 1] and not los[1, 0]
    assert los[0, 2] and los[1, 2] and los[0, 3] and np.all(np.diag(los))
    touching = (((5.0, 0.0), (5.0, 3.0)),)  # ends on the link: not a proper crossing
    assert line_of_sight(pts, touching)[0, 1]
    assert SCENARIOS["torgau"].walls  # the built-in scenario is not trivially all-LOS


def test_channel_model_classes_and_determinism():
    los = np.zeros(200_000, bool)
    los[::2] = True
    e1 = sample_range_errors(np.random.default_rng(1), los)
    e2 = sample_range_errors(np.random.default_rng(1), los)
    np.testing.assert_array_equal(e1, e2)
    m = ChannelModel()
    lo, nl = e1[los], e1[~los]
    assert np.median(lo) == pytest.approx(m.los_bias, abs=0.03)
    assert np.median(nl) > np.median(lo)
    assert np.mean(nl > m.outlier_min) >= m.nlos_outlier_prob * 0.9
    # without the exponential tail, everything beyond 10 m is a gross outlier from the stated interval
    no_tail = ChannelModel(nlos_tail_prob=0.0)
    e3 = sample_range_errors(np.random.default_rng(2), np.zeros(100_000, bool), no_tail)
    gross = e3[e3 > 10]
    assert gross.min() >= m.outlier_min and gross.max() <= m.outlier_max
    assert gross.size / e3.size == pytest.approx(m.nlos_outlier_prob, rel=0.1)
    zero = ChannelModel(los_sigma=0.0, los_tail_prob=0.0, los_outlier_prob=0.0)
    np.testing.assert_array_equal(sample_range_errors(np.random.default_rng(0), np.ones(5, bool), zero), 0.2)


def test_cli_simulate_stats_calibrate_evaluate(tmp_path):
    ds_path = tmp_path / "small.h5"
    p = run_cli("simulate", "mesh", "-o", ds_path, "--scenario", "small", "--seed", "3", "--json")
    assert p.returncode == 0, p.stderr
    info = json.loads(p.stdout)
    assert info["nodes"] == 6 and info["epochs"] == 200
    ds = hdf5.read(ds_path)
    np.testing.assert_array_equal(ds.range, simulate("small", seed=3).range)

    p = run_cli("stats", ds_path, "--json")
    assert p.returncode == 0, p.stderr
    got = json.loads(p.stdout)["groups"]
    want = metrics.ranging_statistics(ds)
    for g in ("los", "nlos", "all"):
        assert set(got[g]) == {
            "share",
            "count",
            "mean_m",
            "median_m",
            "variance_m2",
            "q1sigma_m",
            "q2sigma_m",
            "q3sigma_m",
            "p25_m",
            "p50_m",
            "p75_m",
        }
        assert got[g]["count"] == want[g]["count"]
        median = float("nan") if got[g]["median_m"] is None else got[g]["median_m"]  # JSON null = NaN
        assert median == pytest.approx(want[g]["median_m"], nan_ok=True)
    assert got["nlos"]["count"] > 0 and got["los"]["count"] > 0

    res_path = tmp_path / "cf.h5"
    p = run_cli("calibrate", ds_path, "--method", "cf", "-o", res_path, "--config", "conf1")
    assert p.returncode == 0, p.stderr
    p = run_cli("evaluate", res_path, "--truth", ds_path, "--json")
    assert p.returncode == 0, p.stderr
    ev = json.loads(p.stdout)
    assert set(ev) == {"method", "dataset", "rmse_m", "final_rmse_m", "aligned_rmse_m", "nodes"}
    assert ev["method"] == "cf" and len(ev["nodes"]) == 6
    assert set(ev["nodes"][0]) == {"id", "rmse_m", "final_error_m", "availability"}
    assert all(0.0 <= n["availability"] <= 1.0 for n in ev["nodes"])
    assert ev["aligned_rmse_m"] is not None and ev["aligned_rmse_m"] < 5.0

    # bad input: one line, exit 2
    assert_one_line_error(run_cli("stats", tmp_path / "missing.h5"), "no such file")
    assert_one_line_error(run_cli("evaluate", res_path, "--truth", res_path), "expected mesh or trajectory")
    assert_one_line_error(run_cli("simulate", "mesh", "-o", tmp_path / "x.h5", "--scenario", "nope"), "unknown")
    assert_one_line_error(run_cli("simulate", "mesh", "-o", tmp_path / "no" / "x.h5"), "does not exist")
