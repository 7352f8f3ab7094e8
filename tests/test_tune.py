"""Tuning: soft tau cut -> hard rule, gradients against finite differences, BFGS improves, CLI."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import assert_one_line_error, mesh_of, random_layout, run_cli
from jaxcal import tune as T
from jaxcal.data import MeshDataset
from jaxcal.io import hdf5
from jaxcal.mesh import grid as G
from jaxcal.mesh.pgp import PGPParams


def make_mesh(n=5, k=5, noise=0.15, seed=0, span=5.0, truth=True) -> MeshDataset:
    rng = np.random.default_rng(seed)
    pos, d = random_layout(rng, n, span)
    r = np.abs(d[None] + rng.normal(0, noise, (k, n, n)))
    return mesh_of(r, pos if truth else None)


# 15 x 15 cells of 1 m; broad posteriors (sigma_r ~ cell) so that tau and sigma_v matter
SMALL = dict(
    cell_m=1.0,
    extent_m=7.0,
    margin_m=10.0,
    top_k=6,
    max_hyp=6,
    tau=0.6,
    sigma_r=0.8,
    sigma_v=0.7,
    r_est=1.5,
    min_refs=2,
    likelihood="dense",
)


def test_soft_cut_reduces_to_hard_rule():
    rng = np.random.default_rng(1)
    cells = G.Grid(n_half=3, cell_m=1.0).cells(jnp.float64)
    for _trial in range(20):
        logp = jnp.asarray(rng.normal(0, 2.0, cells.shape[0]))
        logp = logp - jax.nn.logsumexp(logp)
        tau = jnp.asarray(rng.uniform(0.1, 0.95))
        pos_h, lw_h = G.top_hypotheses(logp, cells, 6, tau)
        pos_s, lw_s = G.soft_hypotheses(logp, cells, 6, tau, jnp.asarray(1e-6))
        w = np.sort(np.exp(np.asarray(logp)))[::-1][:6]
        before = np.concatenate([[0.0], np.cumsum(w)[:-1]])
        if np.min(np.abs(before - float(tau))) < 1e-3:  # a cut exactly at tau: the two rules differ
            continue
        np.testing.assert_array_equal(np.asarray(pos_h), np.asarray(pos_s))
        np.testing.assert_allclose(np.exp(np.asarray(lw_s)), np.exp(np.asarray(lw_h)), atol=1e-9)
    # a warm cut keeps some weight on the cells past tau: it is a relaxation, not the same rule
    _, lw_warm = G.soft_hypotheses(logp, cells, 6, tau, jnp.asarray(0.3))
    assert np.isfinite(np.asarray(lw_warm)).all()


@pytest.mark.parametrize("kind, model", [("truth", "gaussian"), ("evidence", "gaussian"),
                                         ("evidence", "mixture")])
def test_gradient_matches_finite_differences(kind, model):
    ds = make_mesh()
    p = PGPParams(**SMALL, range_model=model)
    prob, _ = T.make_problem(ds, p, None, kind, tau_temp=0.1, est_temp=5.0)
    mix = {"nlos_weight": 0.3, "nlos_mean_m": 1.2} if model == "mixture" else {}
    theta = T.theta_of(0.8, 0.7, 0.6, jnp.float64, **mix)
    assert theta.shape == (len(T.tuned_names(model)),)
    f = jax.jit(T.objective)
    g = np.asarray(jax.jit(jax.grad(T.objective))(theta, prob))
    assert np.all(np.isfinite(g)) and np.any(np.abs(g) > 1e-6)
    h = 1e-5
    fd = np.array(
        [
            (float(f(theta.at[i].add(h), prob)) - float(f(theta.at[i].add(-h), prob))) / (2 * h)
            for i in range(theta.shape[0])
        ]
    )
    # central differences in float64: truncation ~h^2, rounding ~1e-16 / h
    np.testing.assert_allclose(g, fd, rtol=2e-4, atol=1e-7)


def test_tune_lowers_objective_and_hard_rule_is_reported():
    ds = make_mesh(k=6, seed=2)
    res = T.tune(
        ds,
        {**SMALL, "sigma_r": 2.0},
        None,
        objective_name="evidence",
        epochs=None,
        tau_temp=0.1,
        max_steps=8,
    )
    assert res.after <= res.before
    assert res.after < res.before - 1e-3  # sigma_r = 2 m is far too wide for 0.15 m noise
    assert res.params["sigma_r"] < 2.0
    assert set(res.params) == {"sigma_r", "sigma_v", "tau"} and 0 < res.params["tau"] < 1
    for d in (res.hard_before, res.hard_after):
        assert set(d) == {"rmse_m", "final_rmse_m", "nlpl"} and np.isfinite(d["nlpl"])


def test_theta_round_trip_with_the_mixture_parameters():
    theta = T.theta_of(0.4, 0.2, 0.85, jnp.float64, nlos_weight=0.15, nlos_mean_m=2.5)
    v = T.values_of(theta)
    assert list(v) == list(T.tuned_names("mixture"))
    np.testing.assert_allclose(
        [v[k] for k in v], [0.4, 0.2, 0.85, 0.15, 2.5], rtol=1e-12
    )
    prm = T._with_theta(
        T.make_problem(make_mesh(k=3), PGPParams(**SMALL, range_model="mixture"), None,
                       "evidence")[0].prm,
        theta,
    )
    np.testing.assert_allclose([float(prm.nlos_weight), float(prm.nlos_mean_m)], [0.15, 2.5])


def test_window_and_truth_required():
    ds = make_mesh(k=6)
    assert T.window(ds, 3).n_epochs == 3 and T.window(ds, 100) is ds
    from jaxcal.errors import JaxcalError

    with pytest.raises(JaxcalError, match="ground truth"):
        T.make_problem(make_mesh(truth=False), PGPParams(**SMALL), None, "truth")


def test_cli_tune_then_calibrate(tmp_path):
    ds = make_mesh(k=6, seed=4)
    f = tmp_path / "m.h5"
    hdf5.write(f, ds)
    sets = [a for k, v in SMALL.items() if k != "cell_m" for a in ("--set", f"{k}={v}")]
    out = tmp_path / "p.json"
    proc = run_cli(
        "tune",
        f,
        "--objective",
        "evidence",
        "--epochs",
        "6",
        "--max-steps",
        "3",
        "-o",
        out,
        "--json",
        *sets,
    )
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(out.read_text())
    assert set(doc["params"]) >= {"sigma_r", "sigma_v", "tau", "top_k"}
    assert (
        doc["tuning"]["objective"] == "evidence"
        and doc["tuning"]["after"] <= doc["tuning"]["before"]
    )
    res = tmp_path / "r.h5"
    proc = run_cli(
        "calibrate",
        f,
        "--method",
        "pgp",
        "--params",
        out,
        "--set",
        "cell_m=1.0",
        "--set",
        "extent_m=7",
        "-o",
        res,
    )
    assert proc.returncode == 0, proc.stderr
    assert abs(hdf5.read(res).params["sigma_r"] - doc["params"]["sigma_r"]) < 1e-12
    # no truth: the truth objective is a one-line error
    g = tmp_path / "nt.h5"
    hdf5.write(g, make_mesh(truth=False))
    assert_one_line_error(
        run_cli("tune", g, "--objective", "truth", "-o", tmp_path / "x.json"), "ground truth"
    )
