"""Tuning: soft tau cut -> hard rule, segmented scan = one scan, gradients against finite
differences, BFGS improves, the guard keeps the start when calibrate does not do better, CLI."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import assert_one_line_error, mesh_of, random_layout, run_cli
from jaxcal import tune as T
from jaxcal import tune_eval as E
from jaxcal.data import MeshDataset
from jaxcal.io import hdf5
from jaxcal.mesh import grid as G
from jaxcal.mesh import pgp
from jaxcal.mesh.pgp import PGPParams
from jaxcal.mesh.segmented import filter_segmented, segment_length


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

# The objective's value and gradient as one compiled program: the tests take the gradient and the
# central differences' values from it (a separate jit of the objective alone compiled the forward
# filter a second time: ~1/4 of each gradient test's time), and tests on the same problem shapes share it.
value_and_grad = jax.jit(jax.value_and_grad(T.objective))


def gradient_and_central_differences(theta, prob, h: float = 1e-5):
    """(gradient, central differences with step h) of `T.objective` at theta, both from `value_and_grad`."""
    g = np.asarray(value_and_grad(theta, prob)[1])
    fd = np.array(
        [
            (float(value_and_grad(theta.at[i].add(h), prob)[0]) - float(value_and_grad(theta.at[i].add(-h), prob)[0]))
            / (2 * h)
            for i in range(theta.shape[0])
        ]
    )
    return g, fd


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


@pytest.mark.parametrize(
    "kind, model, n",
    [("truth", "gaussian", 5), ("nlpl", "gaussian", 5), ("nlpl", "mixture", 5), ("evidence", "gaussian", 7)],
)
def test_gradient_matches_finite_differences(kind, model, n):
    ds = make_mesh(n=n)
    p = PGPParams(**SMALL, range_model=model)
    prob, _ = T.make_problem(ds, p, None, kind, tau_temp=0.1, est_temp=5.0)
    assert prob.kind == kind  # 7 nodes: pairs to hold out
    mix = {"nlos_weight": 0.3, "nlos_mean_m": 1.2} if model == "mixture" else {}
    theta = T.theta_of(0.8, 0.7, 0.6, jnp.float64, **mix)
    assert theta.shape == (len(T.tuned_names(model)),)
    g, fd = gradient_and_central_differences(theta, prob)
    assert np.all(np.isfinite(g)) and np.any(np.abs(g) > 1e-6)
    # central differences in float64: truncation ~h^2, rounding ~1e-16 / h
    np.testing.assert_allclose(g, fd, rtol=2e-4, atol=1e-7)


def test_tune_lowers_objective_and_hard_rule_is_reported():
    ds = make_mesh(k=6, seed=2)
    start = {**SMALL, "sigma_r": 2.0}
    steps = []
    res = T.tune(
        ds,
        start,
        None,
        objective_name="evidence",
        tau_temp=0.1,
        max_steps=8,
        progress=lambda n: steps.append(n),
    )
    assert res.after < res.before - 1e-3  # sigma_r = 2 m is far too wide for 0.15 m noise
    assert res.tuned["sigma_r"] < 2.0 and len(steps) == res.steps >= 1
    assert set(res.params) == {"sigma_r", "sigma_v", "tau"} and 0 < res.params["tau"] < 1
    # the guard's figures are calibrate's run (hard cut, whole dataset) of start and tuned values
    for got, p in ((res.hard_before, start), (res.hard_after, {**start, **res.tuned})):
        want = E.hard_metrics(ds, p, None)
        assert {k: got[k] for k in want} == want
    # 5 nodes: one pair among the non-anchors, too few to hold out: the guard compares the NLPL
    assert np.isnan(res.hard_before["heldout_m"]) and res.hard_key == "nlpl"
    assert res.settings["objective_used"] == "nlpl"
    assert res.accepted == (res.hard_after["nlpl"] < res.hard_before["nlpl"])
    assert res.params == (res.tuned if res.accepted else res.start)


def test_pair_folds_partition_and_heldout_error():
    folds = E.pair_folds(9, 3, seed=1)
    total = sum(f.astype(int) for f in folds)
    want = np.zeros((9, 9), int)
    want[3:, 3:] = 1
    np.fill_diagonal(want, 0)
    np.testing.assert_array_equal(total, want)  # every pair among nodes >= 3 in exactly one fold
    assert all((f == f.T).all() for f in folds) and E.pair_folds(4, 2) == []
    # noise-free ranges: the held-out pairs are predicted to within the grid's quantisation
    ds = make_mesh(n=7, k=6, noise=0.0, seed=6)
    err = E.heldout_range_error(ds, SMALL, None, n_folds=2)
    assert 0 <= err < SMALL["cell_m"]
    # wrong ranges on the held-out pairs raise it by about their offset
    r = ds.range.copy()
    r[:, 3:, 3:] += 2.0
    import dataclasses

    bad = dataclasses.replace(ds, range=r)
    assert E.heldout_range_error(bad, SMALL, None, n_folds=2) > err + 1.0


def test_guard_keeps_the_start_when_calibrate_does_worse(monkeypatch):
    ds = make_mesh(k=6, seed=3)

    # an optimiser that ends far off (sigma_r = 40 m) on a surrogate that calls it better (the
    # failure of issue 17: a short, coarse window liked values that made calibrate's run worse)
    def bad_fit(theta0, prob, *a, **k):
        return theta0.at[0].set(np.log(40.0)), 1, True, "converged", 1.0, 0.5

    monkeypatch.setattr(T, "_bfgs", bad_fit)
    res = T.tune(ds, SMALL, None, objective_name="truth", tau_temp=0.1)
    assert res.tuned["sigma_r"] == pytest.approx(40.0) and res.after < res.before
    assert res.hard_after["rmse_m"] > res.hard_before["rmse_m"]
    assert not res.accepted and res.params == res.start
    assert res.params["sigma_r"] == pytest.approx(SMALL["sigma_r"])


def test_paired_gain_t_equals_scipy_paired_t_test(rng):
    from scipy import stats

    before = rng.uniform(0.2, 1.0, 30)
    after = before - rng.normal(0.01, 0.05, 30)
    after[[3, 7]] = np.nan  # pairs without an estimate in one run are left out
    ok = np.isfinite(after)
    want = stats.ttest_rel(before[ok], after[ok]).statistic
    assert E.paired_gain_t(before, after) == pytest.approx(want, rel=1e-12)
    assert np.isnan(E.paired_gain_t(before[:1], after[:1]))
    assert E.paired_gain_t(np.ones(4), np.zeros(4)) == np.inf


@pytest.mark.parametrize("gain, accepted", [(0.001, False), (0.2, True)])
def test_held_out_guard_needs_a_gain_beyond_the_pairs_scatter(monkeypatch, rng, gain, accepted):
    """The tuned values lower the mean held-out error in both cases; a gain far inside the pairs'
    scatter (t < 1) keeps the start, a clear one (t >> 1) is written."""
    ds = make_mesh(n=7, k=6, seed=3)
    base = rng.uniform(0.1, 0.5, 12)
    noise = rng.normal(0.0, 0.05, 12)
    noise -= noise.mean()  # the mean gain is exactly `gain`; its scatter is the noise's

    def pair_errors(dataset, params, config, *a, **k):
        moved = float(np.asarray(params.sigma_r)) != pytest.approx(SMALL["sigma_r"])
        return base - (gain + noise if moved else 0.0)

    monkeypatch.setattr(E, "heldout_pair_errors", pair_errors)
    monkeypatch.setattr(T, "_bfgs", lambda theta0, prob, *a, **k: (theta0.at[0].add(0.1), 1, True, "ok", 1.0, 0.5))
    res = T.tune(ds, SMALL, None, objective_name="evidence", tau_temp=0.1)
    assert res.hard_key == "heldout_m"
    assert res.hard_after["heldout_m"] < res.hard_before["heldout_m"]
    t = res.settings["guard_gain_t"]
    assert (t > T.GUARD_T) == accepted and res.accepted == accepted
    assert res.params == (res.tuned if accepted else res.start)
    # calibrate's plain run of the tuned values only when they are written
    assert ("rmse_m" in res.hard_after) == accepted


@pytest.mark.parametrize("likelihood", ["dense", "window"])
def test_segmented_scan_equals_one_scan(likelihood):
    """Checkpointed segments (7 epochs as 3 + 3 + a tail of 1) = the one-scan filter: values (also
    on the window fast path, whose windowed epochs run inside the segments) and gradients."""
    ds = make_mesh(n=6, k=7, seed=5)
    p = PGPParams(**{**SMALL, "likelihood": likelihood, "window_m": 5.0, "window_small_m": 0.0})
    cfg, prm, inp, lp0, _ = pgp.prepare(ds, p, None, "pgp")
    st1, out1 = pgp.run_filter(cfg, prm, inp, lp0)
    st2, out2 = filter_segmented(cfg, prm, inp, lp0, segment=3)
    for a, b in zip(jax.tree.leaves(out1), jax.tree.leaves(out2), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(st1.logpost), np.asarray(st2.logpost), atol=1e-12)
    # about sqrt(K), a divisor of K when one is as good (one scan body, no shorter last segment)
    assert segment_length(2000) == 50 and segment_length(200) == 20 and segment_length(1) == 1
    assert segment_length(499) == 23  # prime: ceil(sqrt(K)) and a last segment of 16
    if likelihood == "window":  # its gradient compiles for minutes; the values are the same code
        return
    import dataclasses

    prob, _ = T.make_problem(ds, p, None, "nlpl", tau_temp=0.1)
    seg3 = dataclasses.replace(prob, segment=3)
    one = dataclasses.replace(prob, segment=7)
    theta = T.theta_of(0.8, 0.7, 0.6, jnp.float64)
    g3 = value_and_grad(theta, seg3)[1]  # compiled: eagerly, the ops outside the scans compiled one by one
    g1 = value_and_grad(theta, one)[1]
    np.testing.assert_allclose(np.asarray(g3), np.asarray(g1), rtol=1e-10)


@pytest.mark.parametrize("ring", [False, True])
def test_remat_pair_loops_equal_the_stored_ones(ring):
    """`remat=True` (the tuning path: each pair's factor recomputed in the backward pass) gives the
    values and gradients of the plain loop, on `grid.node_loglik_sparse` and on the kernel-image
    `fast.ring_loglik_grid` (its exact pairs and, for a node with scattered hypotheses, its
    `pair_loglik` fallback)."""
    from jaxcal.mesh import fast as F

    rng = np.random.default_rng(7)
    grid = G.Grid(n_half=6, cell_m=0.5)
    cells = grid.cells(jnp.float64)
    n, h = 4, 3
    idx = rng.integers(0, cells.shape[0], (n, h))
    idx[1] = idx[1, 0]  # node 1: one cell thrice (fits the ring block); the others scattered
    pos = cells[idx]
    lw = jnp.asarray(np.log(rng.dirichlet(np.ones(h), n)))
    z = jnp.asarray(rng.uniform(0.5, 3.0, n))
    use = jnp.asarray([True, True, False, True])

    def f(sig, lw, remat):
        s = jnp.full((n,), sig)
        if ring:
            ll = F.ring_loglik_grid(grid, pos, lw, s, z, use, 0.05, remat=remat)
        else:
            ll = G.node_loglik_sparse(cells, pos, lw, s, z, use, 0.05, remat=remat)
        return jnp.sum(jnp.sin(ll))  # a non-trivial cotangent per cell

    for remat in (False, True):
        v, g = jax.value_and_grad(f, argnums=(0, 1))(jnp.asarray(0.4), lw, remat)
        if not remat:
            want = (v, g)
    np.testing.assert_allclose(float(v), float(want[0]), rtol=1e-13)
    for a, b in zip(g, want[1], strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-11, atol=1e-13)
    assert float(jnp.abs(want[1][0])) > 0


def test_window_path_gradient_matches_finite_differences():
    """The gradient through calibrate's fast-path configuration (`likelihood="window"`: its
    full-grid epochs by kernel images with per-pair `jax.checkpoint`, its cond branches
    checkpointed) against central differences. (This tiny case never reaches a windowed epoch;
    benchmarks/tuning_grad_cost.py compares torgau's gradients, mostly windowed epochs, with the
    unpatched filter's.)"""
    ds = make_mesh(n=6, k=7, seed=5)
    p = PGPParams(**{**SMALL, "likelihood": "window", "window_m": 5.0, "window_small_m": 0.0})
    prob, _ = T.make_problem(ds, p, None, "nlpl", tau_temp=0.1)
    assert prob.cfg.window == 5
    theta = T.theta_of(0.8, 0.7, 0.6, jnp.float64)
    g, fd = gradient_and_central_differences(theta, prob)
    assert np.all(np.isfinite(g)) and np.any(np.abs(g) > 1e-6)
    np.testing.assert_allclose(g, fd, rtol=2e-4, atol=1e-7)


def test_tail_gradient_starts_from_calibrates_run():
    """`tail`: the held-out folds' runs split at the tail's first epoch score the pairs exactly as
    `heldout_pair_errors` (so the guard reuses them), and the objective on the last epochs from
    those states has the gradient of its finite differences."""
    ds = make_mesh(n=7, k=9, seed=4)
    p = PGPParams(**{**SMALL, "likelihood": "window", "window_m": 5.0, "window_small_m": 0.0})
    pairs, states = E.heldout_split(ds, p, None, 6)
    np.testing.assert_array_equal(pairs, E.heldout_pair_errors(ds, p, None))
    assert len(states) == 2
    with jax.enable_x64(True):
        prob, _ = T.make_problem(ds, p, None, "evidence", tau_temp=0.1, est_temp=5.0, tail_from=6, states=states)
        assert prob.inp.z.shape[0] == 3 and prob.k0 == 6
        assert jax.tree.leaves(prob.state)[0].shape[0] == 2  # one state per fold
        theta = T.theta_of(0.8, 0.7, 0.6, jnp.float64)
        g, fd = gradient_and_central_differences(theta, prob)
        assert g.shape == (3,)
    assert np.all(np.isfinite(g)) and np.any(np.abs(g) > 1e-6)
    np.testing.assert_allclose(g, fd, rtol=2e-4, atol=1e-7)
    # tune with a tail: the guard's start figure is that of calibrate's run, unchanged by the split
    res = T.tune(ds, p, None, objective_name="evidence", tau_temp=0.1, max_steps=1, tail=3)
    assert res.settings["grad_from"] == 6
    assert res.hard_before["heldout_m"] == pytest.approx(E.heldout_range_error(ds, p, None))


def test_bfgs_stops_when_the_objective_stops_falling(monkeypatch):
    """On a rippled plateau (large gradients, values within 2e-4) BFGS stops early: at an accepted
    step that gains less than rtol, or after `PATIENCE` rejected steps in a row."""
    monkeypatch.setattr(T, "objective", lambda theta, prob: 1.0 + 1e-4 * jnp.sin(1e4 * theta[0]))
    seen = []
    theta, steps, ok, message, first, last = T._bfgs(jnp.zeros(3), None, 1e-3, 1e-4, 50, lambda k, v: seen.append(v))
    assert steps <= T.PATIENCE + 1 < 50 and not ok
    assert message in (f"no progress in {T.PATIENCE} steps", "last step gained < 0.001 (relative)")
    assert len(seen) == steps and max(seen) - min(seen) <= 2e-4 and last <= first


def test_bfgs_values_are_the_objective_at_start_and_end(monkeypatch):
    """`_bfgs` reports the objective at the start and at the point it returns from the solver's
    own evaluations (no extra runs): the same numbers as evaluating the objective there. A second run
    on the same shapes reuses the compiled step (no new trace of the objective) and ends at the same point."""
    traces = []

    def f(theta, prob):
        traces.append(1)  # runs only when JAX traces it
        c, w = jnp.asarray([1.0, -2.0, 0.5], theta.dtype), jnp.asarray([1.0, 3.0, 0.2], theta.dtype)
        return jnp.sum((theta - c) ** 2 * w) + 0.1

    monkeypatch.setattr(T, "objective", f)
    theta0 = jnp.zeros(3, jnp.float32)
    seen = []
    theta, steps, ok, message, first, last = T._bfgs(theta0, None, 1e-6, 1e-8, 30, lambda k, v: seen.append(v))
    traced = len(traces)
    assert first == float(f(theta0, None)) and last == float(f(theta, None)) == seen[-1]
    assert last < 0.1 + 1e-3 < first and steps <= 30
    del traces[traced:]  # the two evaluations just above
    again = T._bfgs(theta0, None, 1e-6, 1e-8, 30)
    assert len(traces) == traced and again[1:] == (steps, ok, message, first, last)
    np.testing.assert_array_equal(np.asarray(again[0]), np.asarray(theta))


def test_theta_round_trip_with_the_mixture_parameters():
    theta = T.theta_of(0.4, 0.2, 0.85, jnp.float64, nlos_weight=0.15, nlos_mean_m=2.5)
    v = T.values_of(theta)
    assert list(v) == list(T.tuned_names("mixture"))
    np.testing.assert_allclose([v[k] for k in v], [0.4, 0.2, 0.85, 0.15, 2.5], rtol=1e-12)
    prm = T._with_theta(
        T.make_problem(make_mesh(k=3), PGPParams(**SMALL, range_model="mixture"), None, "evidence")[0].prm,
        theta,
    )
    np.testing.assert_allclose([float(prm.nlos_weight), float(prm.nlos_mean_m)], [0.15, 2.5])


def test_consensus_with_the_truth_as_reference_is_the_truth_objective():
    """`consensus` is `truth` with the batch fit in place of the truth: given the true positions as
    its reference it equals `truth` (value and gradient; hard figure `consensus_m` = `rmse_m`)."""
    ds = make_mesh(n=6, k=5, seed=7)
    p = PGPParams(**SMALL)
    true = T.truth_in_filter_order(ds, None, np.arange(ds.n_nodes))  # dataset order, config frame
    want, order = T.make_problem(ds, p, None, "truth", tau_temp=0.1)
    got, order2 = T.make_problem(ds, p, None, "consensus", tau_temp=0.1, reference=true)
    assert got.kind == "consensus" and (order == order2).all()
    theta = T.theta_of(0.8, 0.7, 0.6, jnp.float64)
    vg = [value_and_grad(theta, q) for q in (want, got)]
    v, g = [float(a) for a, _ in vg], [np.asarray(b) for _, b in vg]
    assert np.isfinite(v[0]) and v[1] == pytest.approx(v[0], rel=1e-12)
    np.testing.assert_allclose(g[1], g[0], rtol=1e-10, atol=1e-14)
    m = E.hard_metrics(ds, p, None, reference=true)
    assert m["consensus_m"] == pytest.approx(m["rmse_m"], rel=1e-6)
    # a node without a reference (the batch fit left it unplaced) is not scored
    part = true.copy()
    part[4] = np.nan
    e = np.asarray(E.hard_run(ds, p, None)[2].estimate, np.float64)  # filter order; the hard run's estimates
    o = np.asarray(order)
    ok = np.isfinite(e).all(-1) & np.isfinite(part[o]).all(-1)[None]
    ok[:, 0] = False
    err = np.where(ok[..., None], e - np.nan_to_num(part[o])[None], 0.0)
    rmse = np.sqrt((err**2).sum() / ok.sum())
    assert E.hard_metrics(ds, p, None, reference=part)["consensus_m"] == pytest.approx(rmse, rel=1e-5)


def test_tune_with_the_consensus_objective(monkeypatch):
    """End to end: the batch fit is the reference of the gradient phase and of the guard (one fit),
    and the guard compares calibrate's track RMSE against it before and after."""
    ds = make_mesh(n=6, k=6, seed=8)
    ref = E.consensus_reference(ds, None)
    true = T.truth_in_filter_order(ds, None, np.arange(ds.n_nodes))
    assert ref.shape == (6, 2) and np.isfinite(ref).all()
    assert np.sqrt(np.mean(np.sum((ref[1:] - true[1:]) ** 2, -1))) < 0.5  # 0.15 m noise: close
    calls = []
    monkeypatch.setattr(E, "consensus_reference", lambda *a: calls.append(1) or ref)
    start = {**SMALL, "sigma_r": 2.0}
    res = T.tune(ds, start, None, objective_name="consensus", tau_temp=0.1, max_steps=3)
    assert len(calls) == 1 and res.hard_key == "consensus_m" and res.settings["consensus_unplaced"] == 0
    assert res.after <= res.before and res.tuned["sigma_r"] != start["sigma_r"]
    want = E.hard_metrics(ds, start, None, ref)
    assert {k: res.hard_before[k] for k in want} == want
    better = res.hard_after["consensus_m"] < res.hard_before["consensus_m"]
    t = res.settings["guard_gain_t"]  # the per-node paired t (NaN when the optimiser did not move)
    assert res.accepted == (better and (np.isnan(t) or t > T.GUARD_T))
    assert res.params == (res.tuned if res.accepted else res.start)


def test_node_sq_errors_against_a_loop(rng):
    """Per node: mean over its localised epochs of the squared distance from the reference; a0,
    nodes never localised and nodes without a reference are NaN. In `hard_metrics_nodes` the same
    figures of calibrate's run, in dataset order."""
    est = rng.normal(0, 1, (7, 5, 2))
    est[2, 3] = np.nan
    est[:, 4] = np.nan  # never localised
    ref = rng.normal(0, 1, (5, 2))
    ref[2] = np.nan  # no reference
    want = [np.nan] * 5
    for n in (1, 3):
        want[n] = np.mean([np.sum((est[k, n] - ref[n]) ** 2) for k in range(7) if np.isfinite(est[k, n]).all()])
    np.testing.assert_allclose(E.node_sq_errors(est, ref), want, rtol=1e-12)
    ds = make_mesh(n=6, k=5, seed=7)
    true = T.truth_in_filter_order(ds, None, np.arange(ds.n_nodes))
    ref = true + rng.normal(0, 0.3, true.shape)
    m, nodes = E.hard_metrics_nodes(ds, SMALL, None, ref)
    _, _, out, order = E.hard_run(ds, SMALL, None)
    np.testing.assert_allclose(nodes[order], E.node_sq_errors(np.asarray(out.estimate), ref[order]), rtol=1e-12)
    assert m == E.hard_metrics(ds, SMALL, None, ref) and E.hard_metrics_nodes(ds, SMALL, None)[1] is None


@pytest.mark.parametrize("gain, accepted", [(0.001, False), (0.2, True)])
def test_consensus_guard_needs_a_gain_beyond_the_nodes_scatter(monkeypatch, rng, gain, accepted):
    """The evidence guard's rule on the consensus figure: the tuned values lower `consensus_m` in
    both cases; per-node gains that are mixed (t <= 1) keep the start, a clear gain is written, and
    the one-line summary says the t."""
    from jaxcal.commands.tune import _summary

    ds = make_mesh(n=7, k=6, seed=3)
    ref = T.truth_in_filter_order(ds, None, np.arange(ds.n_nodes))
    base = np.concatenate([[np.nan], rng.uniform(0.5, 1.0, 6)])  # a0 is not scored
    noise = np.concatenate([[0.0], rng.normal(0.0, 0.05, 6)])
    noise[1:] -= noise[1:].mean()  # the mean gain is exactly `gain`; its scatter is the noise's

    def nodes_of(dataset, params, config, reference=None):
        moved = float(np.asarray(params.sigma_r)) != pytest.approx(SMALL["sigma_r"])
        nodes = base - (gain + noise if moved else 0.0)
        return {"rmse_m": 0.3, "nlpl": 2.0, "consensus_m": float(np.sqrt(np.nanmean(nodes)))}, nodes

    monkeypatch.setattr(E, "consensus_reference", lambda *a: ref)
    monkeypatch.setattr(E, "hard_metrics_nodes", nodes_of)
    monkeypatch.setattr(T, "_bfgs", lambda theta0, prob, *a, **k: (theta0.at[0].add(0.1), 1, True, "ok", 1.0, 0.5))
    res = T.tune(ds, SMALL, None, objective_name="consensus", tau_temp=0.1)
    assert res.hard_key == "consensus_m" and res.hard_after["consensus_m"] < res.hard_before["consensus_m"]
    t = res.settings["guard_gain_t"]
    assert t == pytest.approx(E.paired_gain_t(base, base - gain - noise), rel=1e-12)
    assert (t > T.GUARD_T) == accepted and res.accepted == accepted
    assert res.params == (res.tuned if accepted else res.start)
    line = _summary(res, "consensus", "p.json")
    assert "\n" not in line and f"t = {t:.2f}" in line
    assert ("tuned values written" if accepted else "within the nodes' scatter") in line


def test_consensus_without_a_batch_fit_falls_back_and_says_so(monkeypatch):
    from jaxcal.commands.tune import _summary
    from jaxcal.errors import JaxcalError

    def no_fit(dataset, config):
        raise JaxcalError("t: the batch fit placed no node: no consensus reference")

    monkeypatch.setattr(E, "consensus_reference", no_fit)
    # 6 epochs: the shapes of `test_tune_lowers_objective...` (its compiled BFGS step and hard runs are reused)
    res = T.tune(make_mesh(k=6, seed=9), SMALL, None, objective_name="consensus", tau_temp=0.1, max_steps=1)
    assert res.objective == "consensus" and res.settings["objective_used"] == "nlpl"  # 5 nodes: no folds
    assert "placed no node" in res.settings["fallback_reason"] and res.hard_key == "nlpl"
    line = _summary(res, "consensus", "p.json")
    assert "\n" not in line and "placed no node" in line and "calibrate's nlpl" in line


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
    t = doc["tuning"]
    assert t["objective"] == "evidence" and t["settings"]["check_epochs"] == 6
    # what was written is what the guard chose
    chosen = t["tuned"] if t["accepted"] else t["start"]
    assert {k: doc["params"][k] for k in chosen} == chosen
    assert t["accepted"] == (t["hard_after"]["nlpl"] < t["hard_before"]["nlpl"])  # 5 nodes
    # without --json: a progress bar (forced on) and one summary line with both hard figures
    proc = run_cli(
        "tune",
        f,
        "--objective",
        "evidence",
        "--max-steps",
        "2",
        "-o",
        tmp_path / "q.json",
        *sets,
        env={"JAXCAL_PROGRESS": "1"},
    )
    assert proc.returncode == 0, proc.stderr
    line = proc.stdout.strip()
    assert "\n" not in line and "calibrate's nlpl" in line and "start sigma_r=" in line
    assert "gradient on 6 epochs at 1 m cells" in line  # what the gradient phase ran on
    assert "tune:" in proc.stderr and "step" in proc.stderr
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
    assert_one_line_error(run_cli("tune", g, "--objective", "truth", "-o", tmp_path / "x.json"), "ground truth")


def test_hard_metrics_are_calibrates_run():
    """The guard's figures are `calibrate` + `evaluate` on the same data and parameters."""
    from jaxcal.metrics import evaluate_mesh
    from jaxcal.sim.mesh import simulate

    ds = T.window(simulate("small", 4), 15)
    p = {"cell_m": 1.0, "sigma_r": 0.4}
    got = E.hard_metrics(ds, p, "conf1")
    res, _ = pgp.run_pgp(ds, p, "conf1")
    ev = evaluate_mesh(res, ds)
    np.testing.assert_allclose(got["rmse_m"], ev["rmse_m"], rtol=1e-6)
    np.testing.assert_allclose(got["final_rmse_m"], ev["final_rmse_m"], rtol=1e-6)


def test_summary_line_units_and_what_was_tuned_on():
    """The one-line summary: the held-out range error in metres, the surrogate named."""
    from jaxcal.commands.tune import _summary

    v = {"sigma_r": 0.3, "sigma_v": 0.25, "tau": 0.9}
    res = T.TuneResult(
        params=v,
        start=v,
        tuned={**v, "sigma_r": 0.27},
        objective="evidence",
        before=1.0,
        after=0.9,
        hard_before={"heldout_m": 1.5, "nlpl": 2.0},
        hard_after={"heldout_m": 1.6, "nlpl": 1.9},
        accepted=False,
        steps=3,
        converged=False,
        message="stopped at 3 steps",
        settings={"epochs": 200, "check_epochs": 2000, "cell_m": 1.0, "check_cell_m": 0.5},
        seconds={},
    )
    line = _summary(res, "evidence", "p.json")
    assert "calibrate's heldout_m (1.5 -> 1.6 m)" in line and "nats" not in line
    assert "gradient on 200 epochs (the first 200 of 2000) at 1 m cells" in line
    assert "kept the start" in line
    tail = T.TuneResult(
        **{
            **{f: getattr(res, f) for f in res.__dataclass_fields__},
            "settings": {**res.settings, "epochs": 2000, "grad_from": 1800, "cell_m": 0.5},
        }
    )
    assert "gradient through the last 200 of 2000 epochs at 0.5 m cells" in _summary(tail, "evidence", "p.json")
    # better on average but within the held-out pairs' scatter: said so, start kept
    noisy = T.TuneResult(
        **{
            **{f: getattr(res, f) for f in res.__dataclass_fields__},
            "hard_after": {"heldout_m": 1.4999, "nlpl": 1.9},
            "settings": {**res.settings, "guard_gain_t": 0.3, "guard_t_min": 1.0},
        }
    )
    line = _summary(noisy, "evidence", "p.json")
    assert "within the held-out pairs' scatter (t = 0.30 <= 1)" in line and "kept the start" in line

    # written: the t that passed; the optimiser did not move; evidence fell back to nlpl
    def variant(**kw):
        return T.TuneResult(**{**{f: getattr(res, f) for f in res.__dataclass_fields__}, **kw})

    good = variant(
        accepted=True,
        params=res.tuned,
        hard_after={"heldout_m": 1.2},
        settings={**res.settings, "guard_gain_t": 3.2, "guard_t_min": 1.0},
    )
    assert "heldout_m 1.5 -> 1.2 m (better by t = 3.20 > 1: tuned values written)" in _summary(good, "evidence", "p")
    still = _summary(variant(tuned=v, hard_after=res.hard_before), "evidence", "p")
    assert "the optimiser did not move: calibrate's heldout_m 1.5 m; kept the start values" in still
    few = variant(
        settings={**res.settings, "objective_used": "nlpl"}, hard_before={"nlpl": 2.0}, hard_after={"nlpl": 2.1}
    )
    line = _summary(few, "evidence", "p")
    assert line.startswith("tune evidence (fewer than 5 nodes, no pair to hold out: nlpl):")
    assert "not better under calibrate's nlpl (2 -> 2.1 nats/range)" in line
