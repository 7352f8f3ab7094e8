"""jaxcal.sim.network: random sites at constant density, radio range, walls (issue #26)."""

import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli
from jaxcal.errors import JaxcalError
from jaxcal.io import hdf5
from jaxcal.sim.mesh import simulate
from jaxcal.sim.network import network_scenario


@pytest.mark.parametrize("n", [10, 60])
def test_constant_density_radio_range_and_frame_near_the_centre(n):
    sc = network_scenario(n, seed=4, range_limit_m=20.0)
    w, h = sc.hall
    assert w * h == pytest.approx(60.0 * n)  # 1 node per 60 m^2 by default
    ds = simulate(sc, seed=4)
    xy = np.asarray(ds.truth)[:, :2]
    d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1))
    measured = np.isfinite(ds.range).any(axis=0)
    assert not measured[d > 20.0].any()  # beyond radio range: never measured
    near = d[np.triu_indices(n, 1)] < 20.0
    assert measured[np.triu_indices(n, 1)][near].mean() > 0.9  # within it: (almost) all measured
    centre = np.array([w / 2, h / 2])
    r = np.hypot(*(xy - centre).T)
    assert set(np.argsort(r)[:3]) == {0, 1, 2}  # conf1 = the three nodes nearest the centre
    assert dict(ds.configs) == {"conf1": (0, 1, 2)}
    if n >= 60:
        assert len(sc.walls) == round(2 * 60.0 * n / 600.0)
        assert (ds.los[np.triu_indices(n, 1)] == 0).any()  # walls make some pairs NLOS


def test_same_seed_same_network_other_seed_other_layout():
    a, b = simulate(network_scenario(12, seed=1), seed=1), simulate(network_scenario(12, seed=1), seed=1)
    np.testing.assert_array_equal(a.range, b.range)
    c = network_scenario(12, seed=2)
    assert not np.allclose(np.asarray(c.positions), np.asarray(a.truth)[:, :2])


@pytest.mark.parametrize(
    "kw",
    [
        {"n_nodes": 3},
        {"n_nodes": 10, "density": 0.0},
        {"n_nodes": 10, "range_limit_m": float("nan")},
        {"n_nodes": 10, "wall_density": -1.0},
        {"n_nodes": 10, "n_epochs": 0},
    ],
)
def test_bad_settings_are_clear_errors(kw):
    with pytest.raises(JaxcalError):
        network_scenario(**kw)


def test_cli_simulates_a_network_and_refuses_bad_options(tmp_path):
    out = tmp_path / "net.h5"
    proc = run_cli(
        "simulate",
        "mesh",
        "--scenario",
        "network",
        "--nodes",
        "15",
        "--epochs",
        "20",
        "--range-limit",
        "18",
        "--seed",
        "3",
        "-o",
        out,
    )
    assert proc.returncode == 0, proc.stderr
    ds = hdf5.read(out)
    assert (ds.n_nodes, ds.n_epochs) == (15, 20)
    assert_one_line_error(run_cli("simulate", "mesh", "--scenario", "network", "-o", out), "--nodes")
    assert_one_line_error(run_cli("simulate", "trajectory", "--nodes", "5", "-o", out), "mesh")
    assert_one_line_error(run_cli("simulate", "mesh", "--nodes", "10", "--density", "-1", "-o", out), "density")
