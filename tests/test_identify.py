"""Identifiability from the measured graph (`mesh/identify.py`), the proxy frame of pgp / cf
(`mesh/frame_choice.py`), and the account of nodes not placed (`mesh/masking.py`, the CLI's; issues #18,
#24 item 1)."""

from __future__ import annotations

import itertools
import json
import logging

import numpy as np
import pytest

from conftest import mesh_of, random_layout, run_cli
from jaxcal.mesh import frame_choice as F
from jaxcal.mesh import identify as I
from jaxcal.mesh import masking as M
from jaxcal.mesh.frame import frame_covariance, to_frame, to_frame_track
from jaxcal.sim.families import FAMILIES, family_mesh

IDS = [f"n{i}" for i in range(12)]


def complete(n: int) -> np.ndarray:
    return ~np.eye(n, dtype=bool)


def drop(a: np.ndarray, *pairs) -> np.ndarray:
    a = a.copy()
    for i, j in pairs:
        a[i, j] = a[j, i] = False
    return a


def test_complete_and_missing_frame_pairs_are_fixed():
    for dim in (2, 3):
        assert I.identify(complete(7), (0, 1, 2), dim).fixed.all()
    for pair in ((0, 1), (0, 2), (1, 2)):
        ident = I.identify(drop(complete(7), pair), (0, 1, 2))
        assert ident.fixed.all() and ident.frame_fixed
        assert ident.missing_frame_links == (pair,)


def test_single_and_two_neighbours_are_not_fixed_with_the_reason():
    a = drop(complete(7), *[(6, k) for k in range(6) if k != 4])
    ident = I.identify(a, (0, 1, 2), ids=IDS[:7])
    assert ident.fixed.tolist() == [True] * 6 + [False]
    assert ident.reason[6] == "n6 ranges only n4"
    b = drop(complete(7), *[(6, k) for k in range(6) if k not in (3, 4)])  # rigid, mirror-ambiguous
    ident = I.identify(b, (0, 1, 2), ids=IDS[:7])
    assert not ident.fixed[6] and ident.reason[6] == "n6 ranges only n3, n4"
    line = M.describe(ident, IDS[:7], "pgp")
    assert line.startswith("pgp: 1 of 7 nodes cannot be placed (n6)") and "\n" not in line


def test_frame_nodes_follow_their_own_mirror_rule():
    # a2 ranging a0 and a1 only: its y > 0 says nothing about the side the others lie on (the frame has a
    # mirror image); the frame triangle itself is fixed by its three ranges
    a = drop(complete(6), *[(2, k) for k in range(3, 6)])
    ident = I.identify(a, (0, 1, 2), ids=IDS[:6])
    assert not ident.frame_fixed and ident.fixed.tolist() == [True] * 3 + [False] * 3
    assert ident.mirror == "n2 ranges only n0, n1"
    assert "frame (n0/n1/n2) has a mirror image (n2 ranges only n0, n1)" in M.describe(ident, IDS[:6])
    # a1 ranging a0 and one more node: reflected through their line, the frame turns
    ident = I.identify(drop(complete(6), *[(1, k) for k in range(3, 6)]), (0, 1, 2), ids=IDS[:6])
    assert ident.mirror == "n1 ranges only n0, n2" and ident.fixed.tolist() == [True] * 3 + [False] * 3
    # the frame triangle alone is rigid as it is
    assert I.identify(complete(3), (0, 1, 2)).frame_fixed
    # a1 ranging a0 only: its x is fixed, but the rest may turn about a0, so the frame is not determined
    a = drop(complete(6), *[(1, k) for k in range(2, 6)])
    ident = I.identify(a, (0, 1, 2))
    assert not ident.frame_fixed and ident.fixed.tolist() == [True, True] + [False] * 4
    # a1 ranging one node other than a0: two points of the x axis
    b = drop(complete(6), *[(1, k) for k in (0, 2, 3, 4)])
    ident = I.identify(b, (0, 1, 2))
    assert not ident.frame_fixed and ident.fixed.tolist() == [True] + [False] * 5


def test_bridge_cluster_and_unconnected_nodes_are_not_fixed():
    n = 9
    a = np.zeros((n, n), dtype=bool)
    a[:5, :5] = True
    a[4:8, 4:8] = True  # joined by node 4 only; node 8 never ranges
    np.fill_diagonal(a, False)
    ident = I.identify(a, (0, 1, 2), ids=IDS[:n])
    assert ident.fixed.tolist() == [True] * 5 + [False] * 4
    assert "not rigidly connected" in ident.reason[5] and ident.reason[8] == "n8 never ranged"


def test_frame_node_never_connected_leaves_only_a0():
    a = drop(complete(6), *[(2, k) for k in range(6) if k != 2])
    ident = I.identify(a, (0, 1, 2), ids=IDS[:6])
    assert not ident.frame_fixed and ident.fixed.tolist() == [True, True] + [False] * 4
    line = M.describe(ident, IDS[:6])
    assert "frame (n0/n1/n2) not determined" in line and "n0-n2" in line and "n1-n2" in line


def test_relabelling_permutes_the_answer(rng):
    for _ in range(20):
        n = 9
        a = np.triu(rng.random((n, n)) < 0.45, 1)
        a = a | a.T
        perm = rng.permutation(n)
        inv = np.argsort(perm)
        ref = I.identify(a, (0, 1, 2))
        got = I.identify(a[np.ix_(perm, perm)], tuple(int(inv[k]) for k in (0, 1, 2)))
        np.testing.assert_array_equal(got.fixed[inv], ref.fixed)


def test_rigidity_agrees_with_counting_on_small_random_graphs(rng):
    # Laman: a graph on n nodes with fewer than 2n - 3 edges is flexible; the node set that is fixed must
    # then miss some node (the frame adds only the 3 gauge constraints).
    for _ in range(30):
        n = int(rng.integers(5, 9))
        a = np.triu(rng.random((n, n)) < 0.5, 1)
        a = a | a.T
        ident = I.identify(a, (0, 1, 2))
        if a.sum() // 2 < 2 * n - 3:
            assert not ident.fixed.all()


@pytest.mark.parametrize("kind", FAMILIES)
def test_families_fix_what_they_should_on_20_seeds(kind):
    for seed in range(20):
        ds = family_mesh(kind, seed, n_epochs=20)
        ident = I.identify_ranges(ds.range, (0, 1, 2), ids=ds.node_ids)
        n = ds.n_nodes
        if kind == "leaf":
            assert not ident.fixed[n - 1] and "ranges only" in ident.reason[n - 1]
        elif kind == "bridge":
            assert not ident.fixed[n // 2 + 1 :].any() and ident.fixed[: n // 2 + 1].sum() >= n // 2 - 1
        else:
            assert ident.frame_fixed, (kind, seed, ident.reason)
            assert ident.n_fixed >= n - 1, (kind, seed, ident.reason)  # 4 % random gaps may strand one


def test_choose_frame_prefers_fixing_more_nodes():
    ds = family_mesh("a0a1", 0, n_epochs=30)
    tri, ident = F.choose_frame(ds.range)
    assert ident.n_fixed == ds.n_nodes and ident.frame_fixed
    assert all(np.isfinite(ds.range[:, i, j]).any() for i, j in itertools.combinations(tri, 2))


def test_to_frame_track_equals_to_frame_per_epoch(rng):
    p = rng.normal(size=(5, 7, 2)) * 10
    p[2, 1] = np.nan  # a1 missing: whole epoch NaN
    out = to_frame_track(p, 3, 1, 4)
    for k in range(5):
        if k == 2:
            assert np.isnan(out[k]).all()
        else:
            np.testing.assert_allclose(out[k], to_frame(p[k], 3, 1, 4), atol=1e-12)


def test_frame_covariance_matches_monte_carlo(rng):
    pts = rng.uniform(0, 20, (6, 2))
    cov = np.stack([np.diag(rng.uniform(0.001, 0.01, 2)) for _ in range(6)])
    lin = frame_covariance(pts, cov, 3, 1, 4)
    chol = np.linalg.cholesky(cov)
    draws = pts[None] + np.einsum("nij,snj->sni", chol, rng.standard_normal((20000, 6, 2)))
    moved = to_frame_track(draws, 3, 1, 4)
    emp = np.stack([np.cov(moved[:, i].T) for i in range(6)])
    # first order against 20,000 draws: sampling error ~ 1 % of the variance, curvature below that
    np.testing.assert_allclose(lin, emp, atol=0.06 * np.abs(emp).max())


def _noisy_mesh(rng, n, k, missing, sigma=0.05):
    pos, d = random_layout(rng, n, 20.0, min_sep=3.0)
    r = d[None] + sigma * rng.standard_normal((k, n, n))
    r = np.where(rng.random((k, n, n)) < 0.03, np.nan, r)
    for i, j in missing:
        r[:, i, j] = r[:, j, i] = np.nan
    ds = mesh_of(r, pos)
    return ds, to_frame(pos, 0, 1, 2)


def test_cf_places_every_node_without_the_a0_a1_range_on_20_seeds(rng):
    from jaxcal.mesh import closed_form

    for _ in range(20):
        ds, truth = _noisy_mesh(rng, 8, 30, [(0, 1)])
        res = closed_form.calibrate(ds)
        assert np.isfinite(res.position).all()
        avail = np.isfinite(res.track_position).all(axis=2).mean(axis=0)
        assert avail.min() >= 0.95
        assert np.sqrt(np.mean(np.sum((res.position - truth) ** 2, axis=1))) < 0.5


def test_pgp_places_every_node_without_the_a0_a1_range(rng):
    from jaxcal.mesh import pgp

    # (the paper's rule, frame="direct", places a0 only here: benchmarks/frame_families.py)
    ds, truth = _noisy_mesh(rng, 8, 40, [(0, 1)], sigma=0.1)
    res, info = pgp.run_pgp(ds, {"cell_m": 1.0})
    assert info.frame != "anchors:0,1,2" and res.frame == "anchors:0,1,2"
    assert np.isfinite(res.position).all()
    avail = np.isfinite(res.track_position).all(axis=2).mean(axis=0)
    assert avail.min() >= 0.95
    err = np.linalg.norm(res.position - truth, axis=1)
    assert err.max() < 1.5  # 1 m cells, a frame built from estimated a0, a1, a2
    assert np.allclose(res.position[0], 0) and res.position[1, 1] == 0 and res.position[2, 1] > 0
    assert (np.linalg.eigvalsh(res.covariance[1:]) >= -1e-12).all()


def test_batch_leaves_a_mirror_ambiguous_node_nan_with_one_warning_line(rng, caplog):
    from jaxcal.mesh import batch

    # 7 nodes, 17 pairs, test_batch's FAST settings: the same compiled fit as test_batch.py
    ds, _ = _noisy_mesh(rng, 7, 3, [(6, k) for k in range(4)])
    with caplog.at_level(logging.WARNING, logger="jaxcal"):
        res = batch.calibrate(ds, {"n_starts": 2, "smacof_iters": 100, "estimate": "map"})
    assert np.isnan(res.position[6]).all() and np.isnan(res.covariance[6]).all()
    assert np.isfinite(res.position[:6]).all()
    lines = [r.getMessage() for r in caplog.records if "cannot be placed" in r.getMessage()]
    assert len(lines) == 1 and "n6 ranges only n4, n5" in lines[0] and "\n" not in lines[0]


def test_cli_summary_evaluate_info_and_config_auto(tmp_path, rng):
    from jaxcal.io import hdf5

    ds, _ = _noisy_mesh(rng, 7, 20, [(6, k) for k in range(5)] + [(0, 1)])
    path = tmp_path / "m.h5"
    hdf5.write(path, ds)
    out = tmp_path / "r.h5"
    p = run_cli("calibrate", path, "--method", "cf", "-o", out)
    assert p.returncode == 0, p.stderr
    assert "cf: 6/7 positions estimated, 1 NOT placed (not fixed by the ranges: n6)" in p.stdout
    warn = [line for line in p.stderr.splitlines() if "cannot be placed" in line]
    assert len(warn) == 1 and "n6 ranges only n5" in warn[0]
    e = run_cli("evaluate", out, "--truth", path, "--json")
    rep = json.loads(e.stdout)
    assert set(rep) == {"method", "dataset", "rmse_m", "final_rmse_m", "aligned_rmse_m", "nodes"}
    assert rep["rmse_m"] is not None and rep["final_rmse_m"] is not None
    assert [nd["id"] for nd in rep["nodes"] if nd["final_error_m"] is None] == ["n6"]
    text = run_cli("evaluate", out, "--truth", path)
    assert "1 of 7 nodes have no estimate (n6)" in text.stdout, text.stdout + text.stderr
    info = run_cli("info", path, "--json")
    s = json.loads(info.stdout)
    assert ["n0", "n1"] in s["never_ranged"] and ["n0", "n6"] in s["never_ranged"]
    a = run_cli("calibrate", path, "--method", "cf", "--config", "auto", "-o", tmp_path / "a.h5")
    assert a.returncode == 0 and a.stdout.startswith("config auto: "), a.stdout + a.stderr


def test_undetermined_frame_warning_names_links_and_suggests_a_frame(rng, caplog):
    from jaxcal.data import Result

    ds, _ = _noisy_mesh(rng, 7, 5, [(2, k) for k in range(7) if k != 2])  # a2 never ranges
    res = Result(ids=ds.node_ids, position=np.zeros((7, 2)), method="cf", dataset="t", frame="anchors:0,1,2")
    with caplog.at_level(logging.WARNING, logger="jaxcal"):
        out = M.mask_result(res, ds.range)
    assert np.isfinite(out.position).all(axis=1).tolist() == [True, True] + [False] * 5
    (line,) = [r.getMessage() for r in caplog.records]
    assert "frame (n0/n1/n2) not determined" in line and "n0-n2" in line and "n2 never ranged" in line
    assert "suggested frame" in line and "--config auto" in line and "fixes 6/7" in line


def test_filter_frame_reaches_the_nodes_a_filter_can_localise(rng):
    """n1-n2 never ranged (so the filter needs a proxy frame) and n7 ranges only n0 and n6: the triple
    (n6, n0, n7) fixes every rigid node, but a filter started there localises nothing else (no node hears
    n7); `filter_frame` picks a triple from which the frame nodes and all the rest are reached, and pgp
    places every node but n7."""
    from jaxcal.mesh import pgp

    pos = np.array([[0, 0], [14, 0], [6, 11], [12, 10], [3, -8], [16, -7], [-6, 5], [-7, -4]], float)
    pos = pos + rng.uniform(-1.5, 1.5, pos.shape)  # a well-conditioned frame (a2 metres off the a0-a1 line)
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    r = d[None] + 0.1 * rng.standard_normal((40, 8, 8))
    for i, j in [(1, 2)] + [(7, k) for k in (1, 2, 3, 4, 5)]:
        r[:, i, j] = r[:, j, i] = np.nan
    ds, truth = mesh_of(r, pos), to_frame(pos, 0, 1, 2)
    adj = I.measured_pairs(ds.range)
    tri = F.filter_frame(ds.range, (0, 1, 2))
    reach = F.trilateration_reach(adj, tri, 3)
    assert tri != (0, 1, 2) and 7 not in tri
    assert reach[:7].all() and not reach[7]
    res, info = pgp.run_pgp(ds, {"cell_m": 1.0})
    assert np.isfinite(res.position[:7]).all()
    assert np.linalg.norm(res.position[:7] - truth[:7], axis=1).max() < 1.5


def test_apply_says_when_fixed_nodes_are_left_unplaced(rng, caplog):
    from jaxcal.mesh import closed_form

    ds, _ = _noisy_mesh(rng, 6, 10, [])
    res = closed_form.calibrate(ds)
    pos = np.array(res.position, copy=True)
    pos[3] = np.nan  # fixed by the ranges, not placed by the method
    ident = I.identify_ranges(ds.range, (0, 1, 2))
    import dataclasses

    with caplog.at_level(logging.WARNING, logger="jaxcal"):
        M.apply(dataclasses.replace(res, position=pos), ident)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "1 of the 6 nodes the ranges fix left unplaced by the method (n3)" in lines[0]


def _mesh_of_graph(rng, adj, k=40, sigma=0.1):
    n = adj.shape[0]
    pos, d = random_layout(rng, n, 20.0, min_sep=3.0)
    r = d[None] + sigma * rng.standard_normal((k, n, n))
    r[:, ~adj] = np.nan
    return mesh_of(r, pos), pos


def test_filter_frame_leaves_a_frame_that_reaches_fewer_fixed_nodes(rng):
    """Every frame pair measured from the first epoch, but each other node ranges only two frame nodes:
    a filter started in (n0, n1, n2) localises nothing else, one started in (n3, n4, n5) everything."""
    a = complete(7)
    a = drop(a, (3, 2), (4, 0), (5, 1), (6, 2))
    ds, _ = _mesh_of_graph(rng, a, k=5)
    assert I.identify_ranges(ds.range, (0, 1, 2)).frame_fixed
    assert F.frame_reach(ds.range, (0, 1, 2)) == (7, 3)
    tri = F.filter_frame(ds.range, (0, 1, 2))
    assert tri != (0, 1, 2) and F.frame_reach(ds.range, tri) == (7, 7)


def test_pgp_reports_in_its_own_frame_when_the_configured_one_has_a_mirror_image(rng, caplog):
    """n2 (a2) ranges only n0 and n1: in the frame (n0, n1, n2) every other node has two placements. pgp
    runs in a triple without n2, says in one line that the result is in that frame, and places every
    node there but n2 (its own mirror image) close to the truth. 6 nodes, 1 m cells, 20 epochs (cheap)."""
    from jaxcal.mesh import pgp
    from jaxcal.metrics import truth_in_result_frame

    a = drop(complete(6), (2, 3), (2, 4), (2, 5))
    ds, _ = _mesh_of_graph(rng, a, k=20)
    with caplog.at_level(logging.WARNING, logger="jaxcal"):  # direct likelihood: one compiled path (~4 s)
        res = pgp.calibrate(ds, {"cell_m": 1.0, "grid_mode": "global", "likelihood": "direct"})
    tri = res.frame_anchors()
    assert tri != (0, 1, 2) and 2 not in tri
    lines = [r.getMessage() for r in caplog.records if "mirror image" in r.getMessage()]
    assert len(lines) == 1 and "frame n0/n1/n2 has a mirror image (n2 ranges only n0, n1)" in lines[0]
    placed = np.isfinite(res.position).all(axis=1)
    assert placed.tolist() == [True, True, False, True, True, True]
    truth = truth_in_result_frame(res, ds.truth)
    assert np.linalg.norm(res.position[placed] - truth[placed], axis=1).max() < 1.5
