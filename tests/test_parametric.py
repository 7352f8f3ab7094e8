"""Parametric baseline (eq. 9): loop reference, the eq. (9) noise, placement, CLI."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from conftest import run_cli
from jaxcal.io import hdf5
from jaxcal.mesh import grid as G
from jaxcal.mesh import parametric
from jaxcal.mesh.frame import to_frame
from jaxcal.mesh.pgp import PGPParams, prepare, run_pgp
from jaxcal.mesh.pgp.kernels import hypotheses
from jaxcal.mesh.pgp_reference import run_reference_for
from test_pgp import SMALL, make_mesh


@pytest.mark.parametrize("order", ["jacobi", "gauss-seidel"])
def test_matches_loop_reference(order):
    ds = make_mesh(noise=0.2, missing=0.2, seed=3)
    p = PGPParams(**SMALL, update_order=order)
    _, info = run_pgp(ds, p, mode="parametric")
    cfg, _, inp, _, _ = prepare(ds, p, None, mode="parametric")
    ref = run_reference_for(p, cfg, inp, mode="parametric")
    np.testing.assert_allclose(info.posterior, ref["posterior"], atol=1e-9)  # x64, rounding only
    np.testing.assert_allclose(info.raw_track, ref["raw"], atol=1e-9)


def test_eq9_noise_is_sigma_r_plus_sqrt_trace():
    """Neighbour with two equally likely cells 2 m apart: one hypothesis at the mean, sigma + 1."""
    grid = G.Grid(n_half=3, cell_m=1.0)
    cells = grid.cells()
    lp = jnp.full((cells.shape[0],), -jnp.inf)
    a = int(np.flatnonzero((np.asarray(cells) == [1.0, 0.0]).all(1))[0])
    b = int(np.flatnonzero((np.asarray(cells) == [-1.0, 0.0]).all(1))[0])
    lp = lp.at[a].set(np.log(0.5)).at[b].set(np.log(0.5))
    p = PGPParams(r_est=3.0, sigma_r=0.3)
    cfg, prm, *_ = prepare(make_mesh(n=4, k=2), p, None, mode="parametric")
    pos, lw, sig = hypotheses(cfg, prm, lp[None], cells)
    np.testing.assert_allclose(pos[0, 0], [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(lw[0], [0.0])
    np.testing.assert_allclose(sig[0], 0.3 + 1.0)  # tr P = var_x = 1 m^2


def test_noise_free_placement_and_cli(tmp_path):
    ds = make_mesh(n=6, k=5, noise=0.0, seed=5, span=8.0)
    res = parametric.calibrate(ds, {"cell_m": 0.5, "sigma_r": 0.3, "sigma_v": 0.3, "margin_m": 1.0})
    err = np.linalg.norm(res.position - to_frame(ds.truth, 0, 1, 2), axis=1)
    assert np.all(err <= 0.5), err
    assert res.method == "parametric"
    src, out = tmp_path / "m.h5", tmp_path / "r.h5"
    hdf5.write(src, make_mesh(n=4, k=4, noise=0.1, seed=11))
    proc = run_cli("calibrate", src, "--method", "parametric", "-o", out, "--set", "cell_m=1.0", "--json")
    assert proc.returncode == 0, proc.stderr
    r = hdf5.read(out)
    assert r.method == "parametric" and r.covariance.shape == (4, 2, 2) and np.isfinite(r.position).all()


def test_covariance_is_the_pair_level_covariance_at_the_filter_estimate(rng):
    """`--method parametric` reports pgp's kind of covariance (`pgp.with_pair_covariance`): the pair-level
    covariance at its estimate, with the estimate's displacement from a robust fit of the pairs as an error the
    network shares (`position_covariance(..., displacement="network")` with the filter's sigma_r); the positions
    are the filter's, unchanged."""
    from jaxcal.mesh.pair_covariance import position_covariance

    ds = make_mesh(n=6, k=30, noise=0.1, seed=int(rng.integers(1 << 20)), span=8.0)
    p = {"cell_m": 0.5, "sigma_r": 0.3, "sigma_v": 0.3, "margin_m": 1.0}
    res = parametric.calibrate(ds, p)
    raw = run_pgp(ds, PGPParams(**p), mode="parametric", posterior=False)[0]
    pair = position_covariance(ds.range, raw.position, raw.frame_anchors(), robust_scale=0.3, displacement="network")
    np.testing.assert_array_equal(res.position, raw.position)
    fixed = np.isfinite(res.covariance).all(axis=(1, 2))
    assert fixed.sum() >= 4
    np.testing.assert_allclose(res.covariance[fixed], pair[fixed], rtol=1e-9, atol=1e-12)
    for c in res.covariance[fixed]:
        assert np.allclose(c, c.T) and np.linalg.eigvalsh(c).min() >= -1e-12
