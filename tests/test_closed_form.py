"""Closed-form baseline: exact on noise-free data, equal to a slow per-epoch reference, NaN not crash."""

from __future__ import annotations

import numpy as np
import pytest

from jaxcal.data import MeshDataset, mesh_true_distances
from jaxcal.errors import JaxcalError
from jaxcal.mesh import closed_form as cf
from jaxcal.mesh.frame import to_frame
from jaxcal.methods import calibrate as calibrate_registered


def _distances(truth, k, rng=None, drop=0.0, noise=0.0):
    d = mesh_true_distances(truth)
    dk = np.repeat(d[None], k, axis=0)
    if rng is not None and noise:
        e = rng.normal(0, noise, dk.shape)
        dk = np.abs(dk + (e + np.swapaxes(e, 1, 2)) / 2)
    if rng is not None and drop:
        m = rng.random(dk.shape) < drop
        m = m | np.swapaxes(m, 1, 2)
        dk = np.where(m, np.nan, dk)
    n = truth.shape[0]
    dk[:, np.arange(n), np.arange(n)] = np.nan
    return dk


def _reference_epoch(d, anchors, min_refs=3, min_ratio=0.1, anchors_only=False):
    """Slow, obviously written version of the documented rule for one (N, N) distance matrix."""
    n = d.shape[0]
    a0, a1, a2 = anchors
    out = np.full((n, 2), np.nan)
    x1 = d[a0, a1]
    if not (np.isfinite(x1) and x1 > 0):
        return out
    pos = {a0: np.zeros(2), a1: np.array([x1, 0.0])}
    x2 = (d[a0, a2] ** 2 - d[a1, a2] ** 2 + x1**2) / (2 * x1)
    rad = d[a0, a2] ** 2 - x2**2
    if np.isfinite(rad) and rad >= 0:
        pos[a2] = np.array([x2, np.sqrt(rad)])
    while True:
        before = dict(pos)
        new = {}
        for i in range(n):
            if i in before:
                continue
            refs = [j for j in before if np.isfinite(d[i, j]) and (not anchors_only or j in anchors)]
            if len(refs) < min_refs:
                continue
            p = np.array([before[j] for j in refs])
            pbar = p.mean(axis=0)
            q = p - pbar
            lam_min, lam_max = np.linalg.eigvalsh(q.T @ q / len(refs))
            if not (lam_min >= min_ratio**2 * lam_max and lam_min > 0):
                continue
            c = (q * q).sum(axis=1) - d[i, refs] ** 2
            y = np.linalg.lstsq(2 * q, c - c.mean(), rcond=None)[0]
            new[i] = pbar + y
        if not new:
            break
        pos.update(new)
    for i, p in pos.items():
        out[i] = p
    return out


@pytest.mark.parametrize("seed", range(12))
def test_exact_on_noise_free_random_geometries(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(4, 12))
    truth = rng.uniform(0, 40, (n, 2))
    while True:  # a frame triangle that is not nearly degenerate (else later nodes are refused)
        anchors = tuple(int(i) for i in rng.choice(n, 3, replace=False))
        q = truth[list(anchors)] - truth[list(anchors)].mean(axis=0)
        lam = np.linalg.eigvalsh(q.T @ q / 3)
        if lam[0] >= 0.1 * lam[1]:
            break
    # some random pairs missing, but never the frame's baseline
    d = _distances(truth, 5, rng, drop=0.15)
    a0, a1, a2 = anchors
    d[:, a0, a1] = d[:, a1, a0] = mesh_true_distances(truth)[a0, a1]
    track = cf.place_epochs(d, anchors)
    want = to_frame(truth, *anchors)
    has = np.isfinite(track).all(axis=2)
    assert has[:, a0].all() and has[:, a1].all()
    err = np.linalg.norm(track - want[None], axis=2)[has]
    assert err.size > 0 and np.max(err) < 1e-6
    # the same data fully connected places every node (random geometries are well spread)
    full = cf.place_epochs(_distances(truth, 1), anchors)
    assert np.isfinite(full).all()
    assert np.max(np.abs(full[0] - want)) < 1e-6


def test_fast_path_equals_slow_reference_on_noisy_data():
    rng = np.random.default_rng(7)
    truth = rng.uniform(0, 30, (9, 2))
    d = _distances(truth, 40, rng, drop=0.35, noise=0.5)
    anchors = (2, 5, 0)
    for params in (
        cf.ClosedFormParams(),
        cf.ClosedFormParams(anchors_only=True),
        cf.ClosedFormParams(min_refs=4, min_spread_ratio=0.4),
    ):
        fast = cf.place_epochs(d, anchors, params)
        slow = np.stack(
            [
                _reference_epoch(d[k], anchors, params.min_refs, params.min_spread_ratio, params.anchors_only)
                for k in range(d.shape[0])
            ]
        )
        np.testing.assert_array_equal(np.isnan(fast), np.isnan(slow))
        np.testing.assert_allclose(fast, slow, atol=1e-9, equal_nan=True)
        assert np.isfinite(fast).any() and np.isnan(fast).any()  # both branches exercised


def test_missing_range_to_a1_loses_availability_exactly_where_needed():
    """The paper's D5B4 case: node x never ranges to a1; it has a0, a2 and one more node y, whose range
    to x exists only at some epochs. x is placeable exactly at those epochs (3 references), and never
    with the anchors-only rule."""
    rng = np.random.default_rng(3)
    truth = np.array([[0.0, 0.0], [20.0, 0.0], [8.0, 15.0], [25.0, 18.0], [14.0, 28.0]])
    x, y = 4, 3
    k = 60
    d = _distances(truth, k)
    d[:, x, 1] = d[:, 1, x] = np.nan  # x - a1 never measured
    link = rng.random(k) < 0.6
    d[~link, x, y] = d[~link, y, x] = np.nan
    ds = MeshDataset(
        name="d5b4",
        node_ids=list("abcxy"[:3]) + ["y", "x"],
        time=np.arange(k) * 0.1,
        range=d,
        truth=truth,
        configs={"c": (0, 1, 2)},
    )
    res = cf.calibrate(ds, config="c")
    has = np.isfinite(res.track_position).all(axis=2)
    np.testing.assert_array_equal(has[:, x], link)
    assert has[:, y].all()
    assert res.track_position[link, x] == pytest.approx(
        np.repeat(to_frame(truth, 0, 1, 2)[x][None], link.sum(), 0), abs=1e-4
    )
    strict = cf.calibrate(ds, params={"anchors_only": True}, config="c")
    assert not np.isfinite(strict.track_position[:, x]).any()
    assert np.isnan(strict.position[x]).all()


def test_unplaceable_epochs_are_nan_not_errors():
    truth = np.array([[0.0, 0.0], [10.0, 0.0], [3.0, 6.0], [7.0, 8.0]])
    d = _distances(truth, 4)
    d[0, 0, 1] = d[0, 1, 0] = np.nan  # no baseline: nothing but NaN
    d[1, 0, 2] = d[1, 2, 0] = 1.0  # triangle inequality broken: negative radicand for a2
    d[1, 1, 2] = d[1, 2, 1] = 12.0
    d[2] = np.nan  # an empty epoch
    track = cf.place_epochs(d, (0, 1, 2))
    assert np.isnan(track[0]).all()
    assert np.isfinite(track[1, :2]).all() and np.isnan(track[1, 2:]).all()
    assert np.isnan(track[2]).all()
    assert np.isfinite(track[3]).all()


def test_calibrate_result_median_frame_and_registry():
    rng = np.random.default_rng(1)
    truth = rng.uniform(0, 20, (6, 2))
    d = _distances(truth, 31, rng, noise=0.2)
    ds = MeshDataset(
        name="m",
        node_ids=[f"n{i}" for i in range(6)],
        time=np.arange(31) * 0.1,
        range=d,
        truth=truth,
        configs={"c1": (3, 1, 4)},
    )
    res = calibrate_registered(ds, "cf", params={"min_spread_ratio": "0.05"}, config="c1")
    assert res.frame == "anchors:3,1,4" and res.method == "cf"
    assert res.track_position.shape == (31, 6, 2)
    assert res.params["min_spread_ratio"] == 0.05
    track = res.track_position
    for i in range(6):
        ok = np.isfinite(track[:, i]).all(axis=1)
        np.testing.assert_allclose(res.position[i], np.median(track[ok, i], axis=0))
    with pytest.raises(JaxcalError, match="min_refs"):
        cf.calibrate(ds, params={"min_refs": 2})
    with pytest.raises(JaxcalError, match="unknown parameter"):
        cf.calibrate(ds, params={"nope": 1})


def test_parameters_do_not_recompile():
    truth = np.random.default_rng(2).uniform(0, 20, (5, 2))
    d = _distances(truth, 3)
    cf.place_epochs(d, (0, 1, 2))
    before = cf._place_all._cache_size()
    cf.place_epochs(d, (1, 2, 3), cf.ClosedFormParams(min_refs=4, min_spread_ratio=0.3, anchors_only=True))
    assert cf._place_all._cache_size() == before


def test_symmetrise_mean_of_both_directions():
    r = np.full((1, 3, 3), np.nan)
    r[0, 0, 1], r[0, 1, 0] = 4.0, 6.0
    r[0, 0, 2] = 3.0
    s = cf.symmetrise(r)
    assert s[0, 0, 1] == s[0, 1, 0] == 5.0
    assert s[0, 0, 2] == s[0, 2, 0] == 3.0
    assert np.isnan(s[0, 1, 2]) and np.isnan(s[0, 0, 0])


@pytest.mark.parametrize("seed", [0, 1])
def test_thin_frame_triangle_is_placed_through_a_well_spread_proxy(seed):
    """a0, a1, a2 almost on a line (spread ratio 0.03 < min_spread_ratio): the paper's rule places
    nothing beyond the frame; the epochs are placed in a well-spread proxy frame instead (issue #18)."""
    rng = np.random.default_rng(seed)
    frame = np.array([[0.0, 0.0], [20.0, 0.0], [10.0, 0.5]])  # thin triangle
    others = rng.uniform((-5.0, -12.0), (25.0, 12.0), (7, 2))
    truth = np.vstack([frame, others])
    d = _distances(truth, 40, rng, noise=0.05)
    ds = MeshDataset(
        name="thin",
        node_ids=[f"n{i}" for i in range(10)],
        time=np.arange(40) * 0.1,
        range=d,
        truth=truth,
        configs={"c": (0, 1, 2)},
    )
    own = cf.place_epochs(cf.symmetrise(d), (0, 1, 2))
    assert np.isfinite(own[:, 3:]).all(axis=2).mean() < 0.5  # the paper's rule stalls
    res = cf.calibrate(ds, config="c")
    avail = np.isfinite(res.track_position).all(axis=2).mean(axis=0)
    assert avail.min() >= 0.95
    err = np.linalg.norm(res.position - to_frame(truth, 0, 1, 2), axis=1)
    assert np.median(err) < 0.5
