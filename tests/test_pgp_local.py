"""Node-local grids (`mesh/local.py`, issue #26) against the full-grid filter; path choice; unplaced nodes."""

from __future__ import annotations

import logging

import jax.numpy as jnp
import numpy as np
import pytest

from conftest import mesh_of, random_layout
from jaxcal.mesh import grid as G
from jaxcal.mesh import local as L
from jaxcal.mesh import pgp
from jaxcal.mesh.pgp import PGPParams, run_pgp

# a site of 9 nodes in 16 x 16 m, ranges within 9 m: several radio ranges across, so the node-local
# grids (L = 2 * (9 + 0.5 + 1) m) are smaller than the full grid around a0. min_refs = 3: a node that
# heard only a0 and a1 (both on the x axis) has a posterior symmetric in y, whose argmax ties the two
# grids may break differently (both right)
SMALL = dict(cell_m=0.5, margin_m=0.5, top_k=8, max_hyp=4, min_refs=3, window_m=4.0, window_small_m=3.0)


def site(rng, k=12, n=9, span=16.0, limit=9.0, noise=0.05):
    while True:
        pos, d = random_layout(rng, n, span, min_sep=1.5)
        pos = pos - pos[0]
        # the frame (0, 1, 2) measured, every node ranging at least 3 others, a node > 14 m from a0
        near = d <= limit
        wide = np.linalg.norm(pos, axis=1).max() > 14.0  # the site wider than one node-local grid
        if wide and near[0, 1] and near[0, 2] and near[1, 2] and (near.sum(1) >= 4).all():
            break
    r = np.repeat(d[None], k, 0) + rng.normal(0, noise, (k, n, n))
    r = np.abs((r + np.swapaxes(r, 1, 2)) / 2)
    r[:, ~near] = np.nan
    return mesh_of(r, pos)


def run_local(ds, params):
    """`run_pgp`'s local path: (cfg, per-epoch outputs, final covariance), nodes in filter order."""
    p = PGPParams(**params)
    setup = pgp.local_setup(ds, p, (0, 1, 2), "pgp", False)
    assert setup is not None
    order, z, dt, lattice, wide = setup
    n = ds.n_nodes
    allowed, need = pgp.neighbour_sets(p, n)
    cfg, kind, log_cells, nbrs = L.setup(p, n, z, allowed, lattice, wide)
    prm = pgp.FilterParams(*(jnp.asarray(getattr(p, f), float) for f in pgp.NUMERIC))
    _, out, cov = L.run_local(cfg, prm, jnp.asarray(allowed), jnp.asarray(need, float), kind, log_cells, nbrs, z, dt)
    return cfg, out, cov


def test_local_grids_equal_the_full_grid_where_they_hold_the_mass(rng):
    """With `localise_m=0` (the global grid's localisation rule) the node-local grids compute the
    full-grid filter's epochs: same tracks (and final covariances) to rounding while no node's mass
    leaves its grids."""
    ds = site(rng)
    base = dict(SMALL, localise_m=0.0, grid_mode="local")
    cfg, out, cov = run_local(ds, base)
    # the reference: the full-grid filter (`run_filter`, one scan) on a grid holding the whole site
    g_cfg, prm, inp, lp0, order = pgp.prepare(ds, PGPParams(**dict(base, extent_m=100.0)), None)
    np.testing.assert_array_equal(order, np.arange(ds.n_nodes))
    st, ref = pgp.run_filter(g_cfg, prm, inp, lp0)
    assert cfg.wide < g_cfg.grid.n_side  # the local grids are smaller than the site
    assert int(np.asarray(out.n_wide).sum()) > 0
    # the claim holds while every node's mass is inside its grids: up to the first epoch in which a
    # node's wide grid could not bound the mass outside (`lost`; a far mode of a just-localised node)
    lost = np.asarray(out.lost) > 0
    k_ok = int(np.argmax(lost)) if lost.any() else lost.size
    a, b = np.asarray(ref.estimate)[:k_ok], np.asarray(out.estimate)[:k_ok]
    np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
    assert np.isfinite(b).any()
    np.testing.assert_allclose(b, a, atol=1e-6, equal_nan=True)
    if k_ok == lost.size:  # the final posteriors too
        cells = g_cfg.grid.cells(float)
        ref_cov = np.stack([np.asarray(G.mean_cov(lp.reshape(-1), cells)[1]) for lp in st.logpost])
        placed = np.isfinite(b[-1]).all(axis=1)
        np.testing.assert_allclose(np.asarray(cov)[placed], ref_cov[placed], atol=1e-6)


def test_auto_takes_local_grids_for_large_sites_only(rng):
    ds = site(rng)
    p = PGPParams(**SMALL)
    assert pgp.local_setup(ds, p, (0, 1, 2), "pgp", False) is not None
    # sites within one radio range (torgau's hall) keep the global grid: their results are unchanged
    short = dict(SMALL, local_m=100.0)
    assert pgp.local_setup(ds, PGPParams(**short), (0, 1, 2), "pgp", False) is None
    assert pgp.local_setup(ds, PGPParams(**dict(SMALL, grid_mode="global")), (0, 1, 2), "pgp", False) is None
    # modes the local grids do not implement keep the global grid
    assert pgp.local_setup(ds, p, (0, 1, 2), "parametric", False) is None
    assert pgp.local_setup(ds, p, (0, 1, 2), "pgp", True) is None
    assert pgp.local_setup(ds, PGPParams(**dict(SMALL, update_order="gauss-seidel")), (0, 1, 2), "pgp", False) is None


def test_node_the_filter_cannot_place_is_nan_with_one_line(rng, caplog):
    ds = site(rng)
    r = np.array(ds.range)
    lone = ds.n_nodes - 1
    keep = np.flatnonzero(np.isfinite(r[0, lone]))[:1]  # one neighbour: a ring, never localised
    r[:, lone, :] = np.nan
    r[:, :, lone] = np.nan
    r[:, lone, keep] = r[:, keep, lone] = np.asarray(ds.range)[:, lone, keep]
    ds2 = mesh_of(r, np.asarray(ds.truth))
    with caplog.at_level(logging.WARNING, logger="jaxcal"):
        res, _ = run_pgp(ds2, dict(SMALL, grid_mode="local"))
    assert np.isnan(res.position[lone]).all() and np.isnan(res.covariance[lone]).all()
    assert np.isfinite(res.position[0]).all()
    lines = [m for m in caplog.messages if "never localised" in m]
    assert len(lines) == 1 and ds.node_ids[lone] in lines[0] and "\n" not in lines[0]


def test_localise_m_is_validated():
    with pytest.raises(Exception, match="localise_m"):
        pgp.validate_params(PGPParams(localise_m=-1.0))
    with pytest.raises(Exception, match="grid_mode"):
        pgp.validate_params(PGPParams(grid_mode="tiles"))


def test_tune_refuses_a_site_calibrate_runs_on_node_local_grids(rng, tmp_path):
    """tune runs the global grid only: on a site where calibrate runs node-local grids it refuses in
    one line (exit 2), never tuning another filter than calibrate's; grid_mode=global is the way out."""
    from conftest import assert_one_line_error, run_cli
    from jaxcal import tune as T
    from jaxcal.errors import JaxcalError
    from jaxcal.io import hdf5

    ds = site(rng)
    assert pgp.uses_local(ds, SMALL) and not pgp.uses_local(ds, dict(SMALL, grid_mode="global"))
    with pytest.raises(JaxcalError, match="node-local"):
        T.tune(ds, SMALL, None)
    path = tmp_path / "wide.h5"
    hdf5.write(path, ds)
    sets = [a for k, v in SMALL.items() for a in ("--set", f"{k}={v}")]
    p = run_cli("tune", path, "-o", tmp_path / "p.json", *sets)
    assert_one_line_error(p, "grid_mode=global")
    assert not (tmp_path / "p.json").exists()


def test_live_calibration_refuses_a_site_calibrate_runs_on_node_local_grids(tmp_path):
    """Live calibration runs the global grid only: where calibrate would run node-local grids it stops
    with one line (the recording goes on), never running another filter than calibrate's."""
    from jaxcal.live import LiveCalibrator
    from test_recorder import live_capture, replay

    cap = tmp_path / "mesh.bin"
    cap.write_bytes(live_capture(200))
    live = LiveCalibrator(params={"local_m": 2.0}, stream=None)  # node-local grids narrower than the site
    rec = replay(cap, "nlink", {"epoch_s": 0.1}, on_flush=live.guarded_update)
    live.guarded_update(rec, final=True)
    assert live.pgp is None and live.error is not None
    assert "node-local" in live.error and "grid_mode=global" in live.error and "\n" not in live.error
    assert rec.build_dataset().n_epochs == 40
