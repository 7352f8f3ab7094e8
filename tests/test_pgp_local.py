"""Node-local grids (`mesh/local.py`, issue #26) against the full-grid filter; path choice; unplaced nodes."""

from __future__ import annotations

import logging

import jax.numpy as jnp
import numpy as np
import pytest

from conftest import mesh_of, random_layout
from jaxcal.mesh import local as L
from jaxcal.mesh import pgp
from jaxcal.mesh.pgp import PGPParams, run_pgp

# a site of 9 nodes in 16 x 16 m, ranges within 9 m: several radio ranges across, so the node-local
# grids (L = 2 * (9 + 0.5 + 1) m) are smaller than the full grid around a0
SMALL = dict(cell_m=0.5, margin_m=0.5, top_k=8, max_hyp=4, min_refs=2, window_m=4.0, window_small_m=3.0)


def site(rng, k=12, n=9, span=16.0, limit=9.0, noise=0.05):
    while True:
        pos, d = random_layout(rng, n, span, min_sep=1.5)
        pos = pos - pos[0]
        # the frame (0, 1, 2) measured, and every node ranging at least 3 others
        near = d <= limit
        if near[0, 1] and near[0, 2] and near[1, 2] and (near.sum(1) >= 4).all():
            break
    r = np.repeat(d[None], k, 0) + rng.normal(0, noise, (k, n, n))
    r = np.abs((r + np.swapaxes(r, 1, 2)) / 2)
    r[:, ~near] = np.nan
    return mesh_of(r, pos)


def run_local(ds, params):
    """`run_pgp`'s local path, returning its per-epoch outputs too."""
    p = PGPParams(**params)
    a = ds.config(None)
    setup = pgp._local_setup(ds, p, a, "pgp", False)
    assert setup is not None
    order, z, dt, lattice, wide = setup
    n = ds.n_nodes
    allowed, need = pgp._neighbour_sets(p, n)
    cfg, kind, log_cells, nbrs = L.setup(p, n, z, allowed, lattice, wide)
    prm = pgp.FilterParams(*(jnp.asarray(getattr(p, f), float) for f in pgp.NUMERIC))
    st, out, cov = L.run_local(cfg, prm, jnp.asarray(allowed), jnp.asarray(need, float), kind, log_cells, nbrs, z, dt)
    return cfg, out


def test_local_grids_equal_the_full_grid_where_they_hold_the_mass(rng):
    """With `localise_m=0` (the global grid's localisation rule) the node-local grids compute the
    full-grid filter's epochs: same tracks to rounding, whenever no node's mass left its grids."""
    ds = site(rng)
    base = dict(SMALL, localise_m=0.0, frame="direct")
    glob, _ = run_pgp(ds, dict(base, grid_mode="global", extent_m=100.0))
    loc, _ = run_pgp(ds, dict(base, grid_mode="local"))
    cfg, out = run_local(ds, dict(base, grid_mode="local"))
    full = pgp._local_setup(ds, PGPParams(**dict(base, extent_m=100.0)), (0, 1, 2), "pgp", False)[3]
    assert cfg.wide < full.n_side  # the local grids are smaller than the site
    assert int(np.asarray(out.lost).sum()) == 0  # every node's mass inside its grids
    assert int(np.asarray(out.n_wide).sum()) > 0
    a, b = np.asarray(glob.track_position), np.asarray(loc.track_position)
    np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
    np.testing.assert_allclose(b, a, atol=1e-6, equal_nan=True)
    np.testing.assert_allclose(loc.covariance, glob.covariance, atol=1e-6, equal_nan=True)


def test_auto_takes_local_grids_for_large_sites_only(rng):
    ds = site(rng)
    p = PGPParams(**SMALL)
    assert pgp._local_setup(ds, p, (0, 1, 2), "pgp", False) is not None
    # sites within one radio range (torgau's hall) keep the global grid: their results are unchanged
    short = dict(SMALL, local_m=100.0)
    assert pgp._local_setup(ds, PGPParams(**short), (0, 1, 2), "pgp", False) is None
    assert pgp._local_setup(ds, PGPParams(**dict(SMALL, grid_mode="global")), (0, 1, 2), "pgp", False) is None
    # modes the local grids do not implement keep the global grid
    assert pgp._local_setup(ds, p, (0, 1, 2), "parametric", False) is None
    assert pgp._local_setup(ds, p, (0, 1, 2), "pgp", True) is None
    assert pgp._local_setup(ds, PGPParams(**dict(SMALL, update_order="gauss-seidel")), (0, 1, 2), "pgp", False) is None


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
    assert np.isfinite(res.position[:3]).all()  # the frame is placed
    lines = [m for m in caplog.messages if "never localised" in m]
    assert len(lines) == 1 and ds.node_ids[lone] in lines[0] and "\n" not in lines[0]


def test_localise_m_is_validated():
    with pytest.raises(Exception, match="localise_m"):
        pgp.validate_params(PGPParams(localise_m=-1.0))
    with pytest.raises(Exception, match="grid_mode"):
        pgp.validate_params(PGPParams(grid_mode="tiles"))
