"""Fast PGP path (`likelihood="window"`) against the direct evaluation; chunked `advance`."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from conftest import mesh_of, random_layout
from jaxcal.data import MeshDataset
from jaxcal.errors import JaxcalError
from jaxcal.mesh import fast as F
from jaxcal.mesh import grid as G
from jaxcal.mesh import pgp
from jaxcal.mesh.pgp import PGPParams, prepare, run_pgp

# 0.25 m cells on a 49 x 49 grid, windows of 16 x 16 cells: the windows are a small part of the grid
FINE = dict(
    cell_m=0.25,
    extent_m=6.0,
    margin_m=10.0,
    top_k=8,
    max_hyp=4,
    tau=0.8,
    sigma_r=0.3,
    sigma_v=0.2,
    r_est=0.6,
    min_refs=2,
    p_out=0.0,
    window_m=4.0,
)


def mesh(k=10, n=6, seed=0, noise=0.05, jump=None) -> MeshDataset:
    """Random nodes in a 5 m square; `jump=(epoch, node, dx)` moves one node from that epoch on."""
    rng = np.random.default_rng(seed)
    pos, d = random_layout(rng, n, 5.0, min_sep=1.2)
    r = np.repeat(d[None], k, 0)
    if jump is not None:
        e, i, dx = jump
        moved = pos.copy()
        moved[i, 0] += dx
        r[e:] = np.linalg.norm(moved[:, None] - moved[None], axis=-1)
    r = np.abs(r + rng.normal(0, noise, r.shape))
    r = (r + np.swapaxes(r, 1, 2)) / 2
    return mesh_of(r, pos)


def run(ds, likelihood, **kw):
    p = PGPParams(**{**FINE, **kw, "likelihood": likelihood})
    cfg, prm, inp, lp0, _ = prepare(ds, p, None)
    st, out = pgp.run_filter(cfg, prm, inp, lp0)
    return cfg, st, out


@pytest.fixture(scope="module")
def jump_runs():
    ds = mesh(k=22, jump=(12, 4, 0.9))
    return run(ds, "window"), run(ds, "direct")


def test_window_equals_direct_and_is_used(jump_runs):
    (cfg_w, st_w, out_w), (cfg_d, st_d, out_d) = jump_runs
    assert cfg_w.window == 16 and cfg_d.window == 0 and cfg_w.grid.n_side == 49
    used = np.asarray(out_w.windowed)
    assert used.sum() >= 4, used  # the windows did run ...
    assert not used[:2].any()  # ... but not before every node is localised
    np.testing.assert_array_equal(np.isnan(out_w.raw), np.isnan(out_d.raw))
    np.testing.assert_allclose(out_w.raw, out_d.raw, atol=1e-9)
    np.testing.assert_allclose(np.exp(st_w.logpost), np.exp(st_d.logpost), atol=1e-9)
    np.testing.assert_allclose(out_w.log_evidence, out_d.log_evidence, atol=1e-7)
    np.testing.assert_array_equal(out_w.n_factors, out_d.n_factors)


def test_window_falls_back_to_full_grid_when_mass_moves(jump_runs):
    """Node 4 jumps 0.9 m at epoch 12: the bound fails, that epoch runs on the full grid, and
    the windows take over again; the estimates follow the direct evaluation throughout."""
    (_, _, out_w), (_, _, out_d) = jump_runs
    used = np.asarray(out_w.windowed)
    first = int(np.argmax(used))
    assert not used[first:].all(), used  # a fallback after the windows had started
    assert used[-1], used  # and windows again at the end
    np.testing.assert_allclose(out_w.estimate, out_d.estimate, atol=1e-9)


def test_outside_bound_bounds_the_full_prior():
    """`fast.outside_bound` is >= the motion update of eq. (7)-(8) at every cell outside the
    window (v dt = 0 and > 0)."""
    grid = G.Grid(n_half=15, cell_m=0.25)
    cells = grid.cells()
    rng = np.random.default_rng(0)
    w = 16
    for step in (0.0, 0.3):
        logp = rng.normal(0, 3.0, cells.shape[0])
        logp[np.linalg.norm(np.asarray(cells) - [0.5, -0.25], axis=1) > 0.6] = -np.inf
        logp -= np.logaddexp.reduce(logp)
        vals, idx = jax.lax.top_k(logp, 6)
        src_idx = np.stack([np.asarray(idx) // grid.n_side, np.asarray(idx) % grid.n_side], -1)
        org = F.window_origin(idx[0], grid.n_side, w)
        prior = np.asarray(G.predict_direct(logp, cells, 6, step, 0.2)).reshape(31, 31)
        inside = np.zeros((31, 31), bool)
        inside[org[0] : org[0] + w, org[1] : org[1] + w] = True
        b = float(F.outside_bound(vals, src_idx, org, 31, w, 0.25, step, 0.2))
        assert prior[~inside].max() <= b + 1e-12
        assert b < prior[inside].max() - 10  # and it is not vacuous


@pytest.mark.parametrize("likelihood", ["window", "direct"])
def test_chunked_advance_equals_one_run(likelihood):
    ds = mesh(k=12, seed=1)
    p = PGPParams(**{**FINE, "likelihood": likelihood, "smoothing": "ema", "alpha": 0.5})
    res, _ = run_pgp(ds, p)
    cfg, *_ = prepare(ds, p, None)
    s = pgp.start(ds.n_nodes, p, (0, 1, 2), radius_m=cfg.grid.n_half * cfg.grid.cell_m)
    assert s.cfg.grid == cfg.grid
    t = np.asarray(ds.time)
    dt = np.diff(t, prepend=t[:1])
    got = []
    for a, b in [(0, 4), (4, 8), (8, 12)]:  # equal chunk lengths: one compilation
        s, est = pgp.advance(s, ds.range[a:b], dt[a:b])
        got.append(est)
    np.testing.assert_allclose(np.concatenate(got), res.track_position, atol=1e-12)
    assert s.epochs == 12
    post = pgp.stream_posterior(s)
    assert post.shape == (6, 49, 49)
    np.testing.assert_allclose(post.sum(axis=(1, 2)), 1.0, atol=1e-9)


def test_stream_bad_input_is_a_clear_error():
    with pytest.raises(JaxcalError, match="anchors"):
        pgp.start(4, FINE, (0, 0, 1))
    s = pgp.start(4, FINE, radius_m=3.0)
    with pytest.raises(JaxcalError, match="advance"):
        pgp.advance(s, np.zeros((2, 5, 5)), np.zeros(2))


def test_host_chunked_driver_equals_one_scan(jump_runs):
    """`run_chunked` (what `run_pgp` runs: window-only chunks without the full grid, full chunks
    where the windows fail, here also at the jump) gives the same epochs as one `run_filter`."""
    ds = mesh(k=22, jump=(12, 4, 0.9))
    cfg, prm, inp, lp0, _ = prepare(ds, PGPParams(**{**FINE, "likelihood": "window"}), None)
    st, out = pgp.run_chunked(cfg, prm, inp, lp0, chunk=8, full_chunk=2)
    (_, st_w, out_w), _ = jump_runs
    np.testing.assert_array_equal(out.windowed, out_w.windowed)
    np.testing.assert_allclose(out.estimate, out_w.estimate, atol=1e-12)
    np.testing.assert_allclose(out.log_evidence, out_w.log_evidence, atol=1e-9)
    np.testing.assert_allclose(np.exp(st.logpost), np.exp(st_w.logpost), atol=1e-12)


@pytest.mark.parametrize("split", [5, 12, 13])
def test_advance_chunked_continues_exactly(split):
    """Two `advance_chunked` calls split at any epoch (before, at and after the jump that sends
    epochs back to the full grid) give `run_chunked`'s epochs and final state: tuning's tail
    starts from the first part's state."""
    ds = mesh(k=22, jump=(12, 4, 0.9))
    cfg, prm, inp, lp0, _ = prepare(ds, PGPParams(**{**FINE, "likelihood": "window"}), None)
    st_w, out_w = pgp.run_chunked(cfg, prm, inp, lp0, chunk=8, full_chunk=2)
    st_a, out_a = pgp.advance_chunked(cfg, prm, inp, pgp.init_state(cfg, lp0), 0, split, 8, 2)
    st_b, out_b = pgp.advance_chunked(cfg, prm, inp, st_a, split, None, 8, 2)
    for a, b, w in zip(jax.tree.leaves(out_a), jax.tree.leaves(out_b), jax.tree.leaves(out_w), strict=True):
        np.testing.assert_array_equal(np.concatenate([np.asarray(a), np.asarray(b)]), np.asarray(w))
    np.testing.assert_array_equal(np.asarray(pgp.full_state(cfg, st_b).logpost), np.asarray(st_w.logpost))


# small windows of 3 m (W = 12) inside the 4 m ones (W = 16): with sigma_v = 0.12 m most windowed
# epochs hold the small window's bound; with 0.2 m none does (each windowed epoch runs on the
# big window) and the jump of node 4 also sends epochs back to the full grid
BRANCHES = {
    "small": dict(sigma_v=0.12, window_small_m=3.0),
    "big+full": dict(sigma_v=0.2, window_small_m=3.0),
    "small-mixture": dict(sigma_v=0.12, window_small_m=3.0, range_model="mixture", p_out=0.05),
}


@pytest.fixture(scope="module", params=sorted(BRANCHES))
def branch_runs(request):
    ds = mesh(k=22, jump=(12, 4, 0.9))
    kw = BRANCHES[request.param]
    return request.param, run(ds, "window", **kw), run(ds, "direct", **kw)


def test_each_window_branch_equals_direct(branch_runs):
    """Small window, big window (after the small one failed) and full-grid fallback each give
    the direct evaluation's posteriors, evidence and estimates."""
    name, (cfg_w, st_w, out_w), (_, st_d, out_d) = branch_runs
    assert (cfg_w.window, cfg_w.window_small) == (16, 12)
    used, small = np.asarray(out_w.windowed), np.asarray(out_w.small)
    assert not (small & ~used).any()
    if name.startswith("small"):
        # tried only with room to spare (`fast.SMALL_WINDOW_MARGIN`), so not in every epoch
        assert small.sum() >= (1 if "mixture" in name else 5), small
    else:
        first = int(np.argmax(used))
        assert used.sum() >= 4 and not small.any(), (used, small)
        assert not used[first:].all(), used  # the full grid after the windows had started
    np.testing.assert_array_equal(np.isnan(out_w.raw), np.isnan(out_d.raw))
    np.testing.assert_allclose(out_w.raw, out_d.raw, atol=1e-9)
    np.testing.assert_allclose(out_w.estimate, out_d.estimate, atol=1e-9)
    np.testing.assert_allclose(np.exp(st_w.logpost), np.exp(st_d.logpost), atol=1e-9)
    np.testing.assert_allclose(out_w.log_evidence, out_d.log_evidence, atol=1e-7)


@pytest.mark.parametrize("p_out", [0.0, 0.05])
@pytest.mark.parametrize("mixture", [False, True])
def test_ring_loglik_equals_node_loglik(p_out, mixture):
    """`fast.ring_loglik` (one kernel image per pair) against `grid.node_loglik` on a window."""
    grid = G.Grid(n_half=30, cell_m=0.25)
    rng = np.random.default_rng(1)
    n, h, w = 6, 4, 16
    org = np.array([10, 25], np.int32)
    hidx = rng.integers(20, 40, (n, 1, 2)) + rng.integers(0, 4, (n, h, 2))
    pos = (hidx - grid.n_half) * grid.cell_m
    lw = rng.normal(0, 1, (n, h))
    lw[:, -1] = -np.inf  # a hypothesis not kept (eq. 10)
    lw -= np.logaddexp.reduce(lw, axis=1, keepdims=True)
    z = rng.uniform(1, 6, n)
    z[2] = np.nan
    use = np.isfinite(z)
    sig = np.full(n, 0.3)
    nlos = (np.float64(0.2), np.float64(1.0)) if mixture else None
    cells = F.window_cells(org, grid, w, np.float64)
    ref = G.node_loglik(cells, pos, lw, sig, z, use, p_out, nlos)
    got, ok = F.ring_loglik(org, w, grid, pos, lw, sig, z, use, p_out, nlos)
    assert bool(ok)
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
    # hypotheses spread wider than the S x S block: refused (the caller uses node_loglik)
    spread = pos.copy()
    spread[0, 1] += 2.0
    assert not bool(F.ring_loglik(org, w, grid, spread, lw, sig, z, use, p_out, nlos)[1])
    # and a neighbour without a range is not checked
    spread_unused = pos.copy()
    spread_unused[2, 1] += 2.0
    assert bool(F.ring_loglik(org, w, grid, spread_unused, lw, sig, z, use, p_out, nlos)[1])
    # factors that underflow in linear space (p_out = 0, Gaussian, ranges 150 sigma off): refused;
    # with the floor p_out > 0 an underflow cannot change a factor
    far = F.ring_loglik(org, w, grid, pos, lw, np.full(n, 0.02), z + 3.0, use, p_out, nlos)[1]
    if p_out > 0 or not mixture:
        assert bool(far) == (p_out > 0)


def _same_run(a, b):
    (st_a, out_a), (st_b, out_b) = a, b
    for x, y in zip(jax.tree.leaves((st_a, out_a)), jax.tree.leaves((st_b, out_b)), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("likelihood, mode", [("direct", "pgp"), ("dense", "parametric")])
def test_segmented_scan_equals_one_scan_bit_for_bit(likelihood, mode):
    """`run_segmented` (the scan in host segments, for progress) is `run_filter`, bit for bit."""
    ds = mesh(k=15, seed=2)
    p = PGPParams(**{**FINE, "cell_m": 0.5, "likelihood": likelihood})
    cfg, prm, inp, lp0, _ = prepare(ds, p, None, mode)
    ticks = []
    seg = pgp.run_segmented(cfg, prm, inp, lp0, segment=6, progress=ticks.append)
    assert ticks == [6, 6, 3]
    _same_run(seg, pgp.run_filter(cfg, prm, inp, lp0))


def test_run_pgp_progress_counts_epochs_and_changes_nothing():
    """The fast path reports its chunks; a progress callback changes no number."""
    ds = mesh(k=22, jump=(12, 4, 0.9))
    p = {**FINE, "likelihood": "window"}
    ticks = []
    res, info = run_pgp(ds, p, progress=ticks.append)
    ref, ref_info = run_pgp(ds, p)
    assert sum(ticks) == 22 and len(ticks) > 1
    np.testing.assert_array_equal(res.track_position, ref.track_position)
    np.testing.assert_array_equal(info.posterior, ref_info.posterior)


def test_calibrate_cli_shows_an_epoch_bar(tmp_path):
    """`jaxcal calibrate --method pgp` advances a bar over the epochs (forced on: stderr a pipe)."""
    from conftest import run_cli
    from jaxcal.io import hdf5
    from test_data import small_mesh

    src = hdf5.write(tmp_path / "m.h5", small_mesh())
    out = tmp_path / "r.h5"
    proc = run_cli(
        "calibrate",
        src,
        "--method",
        "pgp",
        "-o",
        out,
        "--set",
        "cell_m=1.0",
        "--set",
        "likelihood=dense",
        env={"JAXCAL_PROGRESS": "1"},
    )
    assert proc.returncode == 0, proc.stderr
    assert "/4 [" in proc.stderr and "epoch" in proc.stderr, proc.stderr
    assert "positions estimated" in proc.stdout
