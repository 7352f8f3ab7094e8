"""PGP grid filter: reference equality, invariants, placement, missing data, compilation, CLI."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import assert_one_line_error, mesh_of, random_layout, run_cli
from jaxcal.data import MeshDataset
from jaxcal.errors import JaxcalError
from jaxcal.io import hdf5
from jaxcal.mesh import grid as G
from jaxcal.mesh import pgp
from jaxcal.mesh.frame import to_frame
from jaxcal.mesh.pgp import PGPParams, prepare, run_pgp
from jaxcal.mesh.pgp_reference import run_reference_for


def make_mesh(n=6, k=6, noise=0.0, missing=0.0, seed=0, span=5.0, never=(), configs=None) -> MeshDataset:
    """Random 2-D nodes, ranges = true distance + Gaussian noise, some missing."""
    rng = np.random.default_rng(seed)
    truth, d = random_layout(rng, n, span)
    r = np.repeat(d[None], k, 0) + rng.normal(0, noise, (k, n, n)) * (noise > 0)
    r = np.abs(r)
    r[rng.random((k, n, n)) < missing] = np.nan
    for i, j in never:
        r[:, i, j] = r[:, j, i] = np.nan
    return mesh_of(r, truth, configs=configs or {})


# one grid for every small test (the margin always reaches the cap: R = 7 m, 15 x 15 cells), so
# most tests
# share one compilation
SMALL = dict(
    cell_m=1.0,
    extent_m=7.0,
    margin_m=10.0,
    top_k=6,
    max_hyp=4,
    tau=0.8,
    sigma_r=0.5,
    sigma_v=0.7,
    r_est=1.5,
    min_refs=2,
)


@pytest.mark.parametrize("order", ["jacobi", "gauss-seidel"])
@pytest.mark.parametrize("likelihood", ["sparse", "dense"])
def test_matches_loop_reference(order, likelihood):
    ds = make_mesh(noise=0.2, missing=0.2, seed=3)
    p = PGPParams(**SMALL, update_order=order, likelihood=likelihood, p_out=0.02)
    res, info = run_pgp(ds, p)
    cfg, _, inp, _, order_idx = prepare(ds, p, None)
    assert list(order_idx) == list(range(6))
    ref = run_reference_for(p, cfg, inp)
    # x64: both are exact up to rounding; 1e-9 leaves room for summation order
    np.testing.assert_allclose(info.posterior, ref["posterior"], atol=1e-9)
    np.testing.assert_array_equal(np.isnan(info.raw_track), np.isnan(ref["raw"]))
    np.testing.assert_allclose(info.raw_track, ref["raw"], atol=1e-9)
    assert np.isfinite(res.position).all()


@pytest.mark.parametrize("likelihood", ["sparse", "window"])
def test_mixture_range_model_matches_loop_reference(likelihood):
    """range_model="mixture" (eq. 11 with the LOS/NLOS kernel) equals the loops' written-out EMG."""
    ds = make_mesh(noise=0.2, missing=0.2, seed=3)
    mix = dict(range_model="mixture", nlos_weight=0.3, nlos_mean_m=0.8, p_out=0.02)
    p = PGPParams(**SMALL, likelihood=likelihood, **mix)
    _, info = run_pgp(ds, p)
    cfg, _, inp, _, _ = prepare(ds, p, None)
    ref = run_reference_for(p, cfg, inp)
    np.testing.assert_allclose(info.posterior, ref["posterior"], atol=1e-9)
    np.testing.assert_allclose(info.raw_track, ref["raw"], atol=1e-9)
    gauss = run_reference_for(p, cfg, inp, nlos_weight=0.0)  # the model did reach the filter
    assert np.abs(info.posterior - gauss["posterior"]).max() > 1e-3


def test_range_kernel_is_the_mixture_density_times_a_constant():
    from scipy import stats

    e = np.linspace(-3.0, 12.0, 301)
    s, w, mean = 0.3, 0.25, 1.5
    got = np.exp(np.asarray(G.range_kernel_log(jnp.asarray(e), s, (w, mean))))
    dens = (1 - w) * stats.norm.pdf(e, scale=s) + w * stats.exponnorm.pdf(e, mean / s, scale=s)
    np.testing.assert_allclose(got, dens * s * np.sqrt(2 * np.pi), rtol=1e-10, atol=1e-300)
    # weight 0 is the paper's Gaussian exactly; no mixture argument is the Gaussian too
    g0 = np.asarray(G.range_kernel_log(jnp.asarray(e), s, (0.0, mean)))
    np.testing.assert_array_equal(g0, np.asarray(G.range_kernel_log(jnp.asarray(e), s)))
    np.testing.assert_allclose(g0, -0.5 * (e / s) ** 2, rtol=1e-12)


def test_moving_nodes_match_reference():
    """v > 0 takes the direct (ring-kernel) motion update; it too equals the loops."""
    ds = make_mesh(noise=0.2, seed=4)
    p = PGPParams(**SMALL, v=2.0)
    _, info = run_pgp(ds, p)
    cfg, _, inp, _, _ = prepare(ds, p, None)
    ref = run_reference_for(p, cfg, inp)
    np.testing.assert_allclose(info.posterior, ref["posterior"], atol=1e-9)
    np.testing.assert_allclose(info.raw_track, ref["raw"], atol=1e-9)


def test_posterior_sums_to_one_every_epoch():
    ds = make_mesh(noise=0.3, missing=0.3, seed=1)
    _, info = run_pgp(ds, SMALL)
    assert info.log_mass.shape == (6, 6)
    np.testing.assert_allclose(info.log_mass, 0.0, atol=1e-9)
    np.testing.assert_allclose(info.posterior.sum(axis=(1, 2)), 1.0, atol=1e-9)


def test_relabelling_non_anchor_nodes_changes_nothing():
    ds = make_mesh(noise=0.2, missing=0.2, seed=2)
    res, _ = run_pgp(ds, SMALL)
    perm = np.array([0, 1, 2, 5, 3, 4])  # new node k is old node perm[k]
    ds2 = MeshDataset(
        name="t",
        node_ids=[ds.node_ids[i] for i in perm],
        time=ds.time,
        range=ds.range[:, perm][:, :, perm],
        truth=ds.truth[perm],
    )
    res2, _ = run_pgp(ds2, SMALL)
    np.testing.assert_allclose(res2.position, res.position[perm], atol=1e-9)
    np.testing.assert_allclose(res2.track_position, res.track_position[:, perm], atol=1e-9)
    # and moving the anchors themselves to other indices via a named configuration
    ds3 = MeshDataset(
        name="t",
        node_ids=[ds.node_ids[i] for i in perm[::-1]],
        time=ds.time,
        range=ds.range[:, perm[::-1]][:, :, perm[::-1]],
        truth=ds.truth[perm[::-1]],
        configs={"c": (5, 4, 3)},
    )
    res3 = pgp.calibrate(ds3, SMALL, config="c")
    np.testing.assert_allclose(res3.position, res.position[perm[::-1]], atol=1e-9)


def test_noise_free_ranges_place_every_node_within_one_cell():
    """Noise-free ranges, and node 4 never ranges to a1 (the paper's D5B4 case, where CF cannot
    trilaterate it): every node ends within one cell of the truth and node 4 is available."""
    ds = make_mesh(n=7, k=6, noise=0.0, seed=5, span=8.0, never=[(4, 1)])
    res = pgp.calibrate(ds, {"cell_m": 0.5, "sigma_r": 0.3, "sigma_v": 0.3, "margin_m": 1.0})
    truth = to_frame(ds.truth, 0, 1, 2)
    err = np.linalg.norm(res.position - truth, axis=1)
    assert np.all(err <= 0.5), err
    assert np.isfinite(res.track_position[-3:, 4]).all()
    assert res.covariance.shape == (7, 2, 2) and np.all(np.isfinite(res.covariance))


def test_epoch_without_ranges_is_prediction_only():
    ds = make_mesh(noise=0.2, seed=6)
    r = ds.range.copy()
    r[3] = np.nan
    r[4] = np.nan
    ds2 = MeshDataset(name="t", node_ids=ds.node_ids, time=ds.time, range=r, truth=ds.truth)
    res, info = run_pgp(ds2, SMALL)
    assert np.all(np.isfinite(info.log_mass))
    np.testing.assert_allclose(info.log_mass, 0.0, atol=1e-9)
    assert np.all(np.isfinite(res.track_position[3:]))
    # prediction only: estimates hardly move across the gap (static prior, no data)
    assert np.max(np.abs(res.track_position[4] - res.track_position[2])) < 0.5


def test_no_recompilation_across_sigma_r_and_tau():
    ds = make_mesh(noise=0.2, seed=8)
    f = eqx.filter_jit(eqx.debug.assert_max_traces(pgp.filter_epochs, max_traces=1))
    outs = []
    for sigma_r, tau in [(0.5, 0.8), (0.3, 0.5), (0.8, 0.95)]:
        cfg, prm, inp, lp0, _ = prepare(ds, PGPParams(**{**SMALL, "sigma_r": sigma_r, "tau": tau}), None)
        st, out = f(cfg, prm, inp, lp0)
        outs.append(np.asarray(out.raw))
    assert not np.allclose(outs[0], outs[1], equal_nan=True)  # the numbers did reach the trace


def test_smoothing_options():
    # 8 epochs: two of run_chunked's 4-epoch chunks, so each smoothing mode (static) compiles one scan; with 6 the
    # last 2 epochs compiled a 1-epoch scan per mode as well (6 compilations instead of 3)
    ds = make_mesh(k=8, noise=0.3, seed=9)
    raw = pgp.calibrate(ds, SMALL)
    ema1 = pgp.calibrate(ds, {**SMALL, "smoothing": "ema", "alpha": 1.0})
    np.testing.assert_allclose(ema1.track_position, raw.track_position, atol=1e-12)
    ema = pgp.calibrate(ds, {**SMALL, "smoothing": "ema", "alpha": 0.5})
    med = pgp.calibrate(ds, {**SMALL, "smoothing": "median-ema", "alpha": 0.5, "median_window": 3})
    # eq. (14) by hand on one node
    t, s = raw.track_position[:, 3], None
    for k in range(t.shape[0]):
        if np.isfinite(t[k]).all():
            s = t[k] if s is None else 0.5 * t[k] + 0.5 * s
    np.testing.assert_allclose(ema.track_position[-1, 3], s, atol=1e-12)
    assert np.isfinite(med.position).all()


def test_snapshots_and_uncertainty_out():
    ds = make_mesh(noise=0.2, seed=10)
    res, info = run_pgp(ds, SMALL, snapshot_epochs=(1, 5))
    assert info.snapshots.shape == (2,) + info.posterior.shape
    np.testing.assert_allclose(info.snapshots[1], info.posterior, atol=1e-12)
    assert res.params["sigma_r"] == SMALL["sigma_r"] and res.params["cell_m"] == 1.0
    # covariance is the posterior's, read as a histogram density: the cell centres' covariance plus
    # cell^2 / 12 per free axis; a0 is exact, a1 varies along x only
    assert np.allclose(res.covariance[0], 0) and np.allclose(res.covariance[1][1], 0)
    gx, gy = np.meshgrid(info.axis_m, info.axis_m, indexing="ij")
    q = res.params["cell_m"] ** 2 / 12
    for i in range(1, ds.n_nodes):
        p = info.posterior[i] / info.posterior[i].sum()
        mx, my = np.sum(p * gx), np.sum(p * gy)
        want = np.array(
            [
                [np.sum(p * (gx - mx) ** 2), np.sum(p * (gx - mx) * (gy - my))],
                [np.sum(p * (gx - mx) * (gy - my)), np.sum(p * (gy - my) ** 2)],
            ]
        )
        want += np.diag([q, q if i != 1 else 0.0])
        np.testing.assert_allclose(res.covariance[i], want, atol=1e-9)
        assert res.covariance[i][0, 0] >= q - 1e-12


@pytest.mark.parametrize(
    "key, value",
    [
        ("tau", 0.0),
        ("sigma_r", -1.0),
        ("update_order", "random"),
        ("top_k", 0),
        ("range_model", "student"),
        ("nlos_weight", 1.0),
        ("nlos_mean_m", 0.0),
    ],
)
def test_bad_parameters_are_clear_errors(key, value):
    ds = make_mesh(n=4, k=2)
    with pytest.raises(JaxcalError, match=key):
        pgp.calibrate(ds, {key: value})


def test_cli_calibrate_pgp(tmp_path):
    ds = make_mesh(n=4, k=4, noise=0.1, seed=11)
    src = tmp_path / "mesh.h5"
    hdf5.write(src, ds)
    out = tmp_path / "res.h5"
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
        "sigma_r=0.4",
    )
    assert proc.returncode == 0, proc.stderr
    res = hdf5.read(out)
    assert res.method == "pgp" and res.params["sigma_r"] == 0.4 and res.params["top_k"] == 32
    assert res.covariance.shape == (4, 2, 2) and res.track_position.shape == (4, 4, 2)
    assert np.isfinite(res.position).all()
    bad = run_cli("calibrate", src, "--method", "pgp", "-o", out, "--set", "nonsense=1")
    assert_one_line_error(bad, "nonsense")


def test_jacobi_and_gauss_seidel_agree_on_clean_data():
    ds = make_mesh(noise=0.05, seed=12)
    a = pgp.calibrate(ds, SMALL)
    b = pgp.calibrate(ds, {**SMALL, "update_order": "gauss-seidel"})
    assert np.max(np.linalg.norm(a.position - b.position, axis=1)) < 0.5
    assert jnp.isfinite(jnp.asarray(b.track_position[-1])).all()
