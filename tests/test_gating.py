"""UWB range-zone gating (jaxcal.trajectory.gating), the simulated yard and `jaxcal gate`."""

from __future__ import annotations

import equinox as eqx
import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli
from jaxcal.sim.places import PlaceConfig, perturb_anchors, simulate_places
from jaxcal.trajectory import gating
from jaxcal.trajectory.gating import Anchors, GateParams, KeyframeDB, ZoneIndex

SMALL = PlaceConfig(
    width_m=90.0,
    height_m=64.0,
    cross_pitch_m=45.0,
    descriptor_dim=16,
    n_anchors_x=2,
    n_anchors_y=2,
    max_range_m=120.0,
)


def _scene(rng, k=300, f=8, a=4, q=25, p_missing=0.4):
    pos = rng.uniform(0, 80, (k, 3))
    desc = rng.normal(size=(k, f))
    anchors = rng.uniform(0, 80, (a, 3))
    cov = np.stack([np.diag(rng.uniform(0.1, 2.0, 3)) for _ in range(a)])
    qpos = rng.uniform(0, 80, (q, 3))
    ranges = np.linalg.norm(qpos[:, None] - anchors[None], axis=-1) + rng.normal(0, 1.0, (q, a))
    ranges[rng.random((q, a)) < p_missing] = np.nan
    return pos, desc, anchors, cov, ranges, rng.normal(size=(q, f))


def _slow_admissible(pos, anchors, sigma, r, delta, k_sigma, rel):
    """Obviously-correct loop: keyframe i admissible iff every heard anchor's zone contains it."""
    out = np.ones(len(pos), bool)
    for i in range(len(pos)):
        for a in range(len(anchors)):
            if not np.isfinite(r[a]) or not np.all(np.isfinite(anchors[a])):
                continue
            w = delta + k_sigma * sigma[a] + rel * r[a]
            if abs(np.linalg.norm(pos[i] - anchors[a]) - r[a]) > w:
                out[i] = False
    return out


def test_zone_mask_equals_numpy_loop(rng):
    pos, desc, anchors, cov, ranges, _ = _scene(rng, k=200)
    anchors[3] = np.nan  # an anchor without estimate never gates
    an = Anchors.from_estimate(anchors, cov)
    sigma = np.sqrt(np.linalg.eigvalsh(cov)[:, -1])
    np.testing.assert_allclose(an.sigma, sigma, rtol=1e-12)
    db = KeyframeDB.build(pos, desc)
    p = GateParams(delta_m=2.5, k_sigma=1.5, range_rel=0.02)
    for r in ranges:
        got = np.asarray(gating.admissible(db, an, jnp.asarray(r), p))
        want = _slow_admissible(pos, anchors, sigma, r, 2.5, 1.5, 0.02)
        assert np.array_equal(got, want)


def test_zones_of_several_anchors_intersect(rng):
    pos, desc, anchors, cov, _, _ = _scene(rng, k=400, a=3)
    db, an, p = (
        KeyframeDB.build(pos, desc),
        Anchors.from_estimate(anchors, cov),
        GateParams(delta_m=4.0),
    )
    r = np.linalg.norm(pos[7] - anchors, axis=1)
    single = [np.asarray(gating.admissible(db, an, jnp.where(jnp.arange(3) == a, r, jnp.nan), p)) for a in range(3)]
    both = np.asarray(gating.admissible(db, an, jnp.asarray(r), p))
    assert np.array_equal(both, single[0] & single[1] & single[2])
    assert both.sum() < min(s.sum() for s in single)  # intersecting really narrows this scene
    assert both[7]


def test_no_range_falls_back_to_full_search(rng):
    pos, desc, anchors, cov, _, qdesc = _scene(rng, k=150)
    db, an = KeyframeDB.build(pos, desc), Anchors.from_estimate(anchors, cov)
    ix = ZoneIndex.build(db, an)
    none = np.full((len(qdesc), len(anchors)), np.nan)
    gated = gating.search(db, ix, an, qdesc, none, GateParams(), top_k=4)
    full = gating.search_full(db, qdesc, top_k=4)
    assert np.array_equal(gated.index, full.index)
    np.testing.assert_allclose(gated.distance, full.distance, rtol=1e-12)
    assert np.all(np.asarray(gated.n_admissible) == len(pos))


@pytest.mark.parametrize("metric", ["cosine", "l2"])
def test_indexed_search_equals_masked_and_a_loop(rng, metric):
    pos, desc, anchors, cov, ranges, qdesc = _scene(rng, k=200, q=30)
    # a query that hears no anchor (every keyframe admissible: the fallback path), on any seed; random
    # missing ranges alone give one in only about half of the seeds (1 - (1 - 0.4^4)^30)
    ranges[0] = np.nan
    db, an = KeyframeDB.build(pos, desc, metric), Anchors.from_estimate(anchors, cov)
    ix, p = ZoneIndex.build(db, an), GateParams(delta_m=3.0)
    batched = gating.search(db, ix, an, qdesc, ranges, p, top_k=5)
    masked = jax.vmap(gating.rank_masked, in_axes=(None, None, 0, 0, None, None))(
        db, an, jnp.asarray(ranges), jnp.asarray(qdesc), p, 5
    )
    assert np.array_equal(batched.index, masked.index)
    n = np.asarray(batched.n_admissible)
    assert (n < 64).any() and (n == len(pos)).any()  # both the gathered-slice path and the fallback ran
    assert np.array_equal(batched.n_admissible, masked.n_admissible)
    np.testing.assert_allclose(batched.distance, masked.distance, rtol=1e-10)
    # vmap over queries equals a Python loop of single-query calls (fixed capacity K: exact)
    one_query = jax.jit(lambda r, q: gating.rank_indexed(db, ix, an, r, q, p, 5, len(pos)))
    for i in range(0, len(qdesc), 7):
        one = one_query(jnp.asarray(ranges[i]), jnp.asarray(qdesc[i]))
        assert np.array_equal(one.index, batched.index[i])
        # brute force: rank the admissible keyframes by distance with NumPy
        mask = _slow_admissible(pos, anchors, np.asarray(an.sigma), ranges[i], 3.0, 2.0, 0.01)
        if metric == "cosine":
            dist = 1 - (desc / np.linalg.norm(desc, axis=1, keepdims=True)) @ (qdesc[i] / np.linalg.norm(qdesc[i]))
        else:
            dist = np.linalg.norm(desc - qdesc[i], axis=1)
        want = np.flatnonzero(mask)[np.argsort(dist[mask], kind="stable")][:5]
        got = np.asarray(one.index)
        assert np.array_equal(got[: want.size], want) and np.all(got[want.size :] == -1)


def test_gating_keeps_true_place_when_errors_within_zone(rng):
    k, a = 400, 3
    pos = rng.uniform(0, 100, (k, 3))
    desc = rng.normal(size=(k, 12))
    truth = rng.uniform(0, 100, (a, 3))
    p = GateParams(delta_m=1.0, k_sigma=2.0, range_rel=0.01)
    sig = np.array([0.5, 1.0, 2.0])
    # anchor error of length <= k_sigma * sigma, range error <= delta + range_rel * range
    u = rng.normal(size=(a, 3))
    est = truth + (u / np.linalg.norm(u, axis=1, keepdims=True)) * 2.0 * sig[:, None] * rng.uniform(0, 1, (a, 1))
    an = Anchors.from_estimate(est, sig[:, None, None] ** 2 * np.eye(3))
    db, ix = KeyframeDB.build(pos, desc), None
    ix = ZoneIndex.build(db, an)
    true_idx = rng.choice(k, 40, replace=False)
    d = np.linalg.norm(pos[true_idx][:, None] - truth[None], axis=-1)
    bound = (1.0 + 0.01 * d) * 0.999
    ranges = d + rng.uniform(-1, 1, d.shape) * bound / 1.01  # keeps |error| < delta + rel * measured range
    res = gating.search(db, ix, an, desc[true_idx], ranges, p, top_k=1)
    assert np.array_equal(np.asarray(res.index[:, 0]), true_idx)
    assert np.all(np.asarray(res.n_admissible) < k)  # and the gate did remove keyframes


def test_gate_params_do_not_recompile(rng):
    pos, desc, anchors, cov, ranges, qdesc = _scene(rng, k=100, q=4)
    db, an = KeyframeDB.build(pos, desc), Anchors.from_estimate(anchors, cov)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def f(p):
        return gating.rank_masked(db, an, jnp.asarray(ranges[0]), jnp.asarray(qdesc[0]), p, 3)

    for delta in (1.0, 2.0, 5.0):
        f(GateParams(delta_m=delta, k_sigma=1.0, range_rel=0.0))


def test_bad_shapes_raise(rng):
    pos, desc, anchors, cov, ranges, qdesc = _scene(rng, k=50, q=3)
    db, an = KeyframeDB.build(pos, desc), Anchors.from_estimate(anchors, cov)
    ix = ZoneIndex.build(db, an)
    with pytest.raises(ValueError, match="descriptors"):
        gating.search(db, ix, an, qdesc[:, :3], ranges)
    with pytest.raises(ValueError, match="ranges"):
        gating.search(db, ix, an, qdesc, ranges[:, :2])
    with pytest.raises(ValueError, match="metric"):
        KeyframeDB.build(pos, desc, "hamming")


def test_simulated_yard_is_repetitive_and_ranges_consistent():
    sc = simulate_places(3, SMALL, n_queries=40)
    k = sc.keyframe_position.shape[0]
    assert sc.keyframe_descriptor.shape == (k, 16) and sc.query_range.shape == (40, 4)
    # repetition: the same spot one aisle over (y + row pitch) looks alike, other places do not
    d = sc.keyframe_descriptor / np.linalg.norm(sc.keyframe_descriptor, axis=1, keepdims=True)
    kp = sc.keyframe_position
    key = {(round(x, 3), round(y, 3)): i for i, (x, y, _) in enumerate(kp)}
    pairs = [
        (i, key[(round(x, 3), round(y + SMALL.row_pitch_m, 3))])
        for i, (x, y, _) in enumerate(kp)
        if (round(x, 3), round(y + SMALL.row_pitch_m, 3)) in key
    ]
    assert len(pairs) > 50
    i, j = np.array(pairs).T
    rnd = np.random.default_rng(0).integers(0, k, (2, 500))
    assert np.mean(np.sum(d[i] * d[j], 1)) > 0.7
    assert abs(np.mean(np.sum(d[rnd[0]] * d[rnd[1]], 1))) < 0.2
    heard = np.isfinite(sc.query_range)
    true = np.linalg.norm(sc.query_position[:, None] - sc.anchor_truth[None], axis=-1)
    err = np.abs(sc.query_range - true)[heard]
    assert np.median(err) < 1.0  # LOS/NLOS mixture: mostly sub-metre
    other = simulate_places(3, SMALL, n_queries=40, anchors=np.array([[10.0, 10.0, 5.0]]))
    assert np.array_equal(other.query_descriptor, sc.query_descriptor)
    assert other.query_range.shape == (40, 1)
    pos, cov = perturb_anchors(np.random.default_rng(0), sc.anchor_truth, 2.0)
    assert cov.shape == (4, 3, 3) and np.allclose(cov[0], 4.0 / 3.0 * np.eye(3))


def test_cli_simulate_end_to_end_and_reader(tmp_path):
    proc = run_cli(
        "gate",
        "--simulate",
        tmp_path,
        "--size",
        "small",
        "--max-anchors",
        "2",
        "-o",
        tmp_path / "out.h5",
        "--json",
        "--top-k",
        "3",
    )
    assert proc.returncode == 0, proc.stderr
    import json

    out = json.loads(proc.stdout)
    assert out["n_queries"] == 60 and out["queries_with_truth"] == 60
    assert 0 < out["mean_anchors_heard"] <= 2
    assert out["mean_admissible"] < out["keyframes"]
    assert out["success_gated"] > out["success_full"]  # seed 0: the repetitive yard fools the full search
    with h5py.File(tmp_path / "out.h5") as f:
        assert f.attrs["jaxcal_format"] == "result"
        assert f["candidates/index"].shape == (60, 3)
        assert f["position"].shape == (60, 3)
    # the contract ranges, assigned by time window, equal the simulated per-query ranges
    from jaxcal.io.places import read_queries

    _, r, ids, _, truth = read_queries(str(tmp_path / "places_queries.h5"), 0.1)
    sc = simulate_places(
        0,
        PlaceConfig(
            width_m=150.0,
            height_m=100.0,
            cross_pitch_m=50.0,
            descriptor_dim=64,
            n_anchors_x=2,
            n_anchors_y=2,
            max_range_m=150.0,
        ),
        n_queries=60,
    )
    np.testing.assert_array_equal(r, sc.query_range.astype(np.float64))
    np.testing.assert_allclose(truth, sc.query_position)
    assert ids == ["A0", "A1", "A2", "A3"]


def test_cli_bad_input_one_line(tmp_path):
    bad = tmp_path / "x.h5"
    bad.write_text("not hdf5")
    assert_one_line_error(run_cli("gate", bad, bad, "--anchors", bad), "x.h5")
    assert_one_line_error(run_cli("gate", bad), "need DB.h5")
    assert_one_line_error(run_cli("gate", "--simulate", tmp_path, "--set", "delta_m=-1"), "delta_m")


def test_one_shot_search_equals_batched(rng):
    pos, desc, anchors, cov, ranges, qdesc = _scene(rng, k=160, q=12)
    db, an = KeyframeDB.build(pos, desc), Anchors.from_estimate(anchors, cov)
    ix, p = ZoneIndex.build(db, an), GateParams(delta_m=2.0)
    batched = gating.search(db, ix, an, qdesc, ranges, p, top_k=3, min_capacity=16)
    for i in range(len(qdesc)):
        one = gating.search_one(db, ix, an, jnp.asarray(ranges[i]), jnp.asarray(qdesc[i]), p, 3, 16)
        assert np.array_equal(one.index, batched.index[i])
        assert int(one.n_admissible) == int(batched.n_admissible[i])
    full = gating.search_one_full(db, jnp.asarray(qdesc[0]), 3)
    assert np.array_equal(full.index, gating.search_full(db, qdesc[:1], 3).index[0])
