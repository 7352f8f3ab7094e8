"""nls's jackknife over route cells (`nls.cell_labels`, `nls.cell_covariances`): an error tied to a place counts
once however often the route passes it."""

import numpy as np
import pytest

from jaxcal.trajectory import nls
from trajectory_campaigns import one_anchor_dataset


def test_cell_jackknife_equals_leave_one_cell_out_refits(rng):
    n, p, g = 70, 4, 7
    jac = rng.normal(size=(n, p))
    cluster = rng.integers(0, g - 1, n)  # cells revisited in any order; cell g - 1 empty (counts for nothing)
    res = rng.normal(size=n) * 0.05 + rng.normal(size=g)[cluster] * 0.3  # an error shared by each cell's entries
    mask = np.ones(n, bool)
    mask[-5:] = False
    cluster[-5:] = g  # padding
    res[:65] -= jac[:65] @ np.linalg.lstsq(jac[:65], res[:65], rcond=None)[0]  # residuals at the LS fit
    out = np.asarray(nls.robust_covariance(np.zeros((p, p)), jac * mask[:, None], res * mask, mask, g, cluster))
    # reference: the linear fit refitted without each non-empty cell (one Gauss-Newton step is exact here)
    y = jac[:65] @ np.ones(p) - res[:65]
    full = np.linalg.lstsq(jac[:65], y, rcond=None)[0]
    used = np.unique(cluster[:65])
    steps = [np.linalg.lstsq(jac[:65][cluster[:65] != c], y[cluster[:65] != c], rcond=None)[0] - full for c in used]
    steps = np.stack(steps)
    np.testing.assert_allclose(out, (used.size - 1) / used.size * steps.T @ steps, rtol=1e-8, atol=1e-12)


def test_cell_labels_number_cells_by_first_visit_and_pad():
    pos = np.array([[[0.5, 0.5, 0], [13.0, 0.5, 0], [0.9, 11.0, 0], [25.0, 1.0, 0], [0.0, 0.0, 0]]])
    mask = np.array([[True, True, True, True, False]])
    labels, n_cells = nls.cell_labels(pos, mask, 12.0)
    assert n_cells == 3 and labels.tolist() == [[0, 1, 0, 2, 3]]


def laps(seed, n_laps=6, zone_m=0.4, noise_m=0.05):
    """A flat loop (radius 15 m) driven `n_laps` times, one anchor 4 m off its centre; on a quarter of the
    loop every range is `zone_m` long (an NLOS zone: the same place, the same error, on every lap)."""
    gen = np.random.default_rng(seed)
    anchor = np.array([[4.0 * np.cos(gen.uniform(0, 6.3)), 4.0 * np.sin(gen.uniform(0, 6.3)), 2.5]])
    period = 20.0
    start = gen.uniform(0, 2 * np.pi)

    def body(t):
        ang = start + 2 * np.pi * t / period
        return np.stack([15 * np.cos(ang), 15 * np.sin(ang), 1.5 * np.sin(3 * ang)], 1), ang + np.pi / 2

    t = np.arange(0, n_laps * period, 0.1)
    rt = np.arange(0.05, t[-1] - 0.05, 0.05)
    pr, _ = body(rt)
    zone = np.mod(np.arctan2(pr[:, 1], pr[:, 0]) - gen.uniform(0, 6.3), 2 * np.pi) < np.pi / 2
    r = np.linalg.norm(pr - anchor[0], axis=1) + 0.1 + zone_m * zone + noise_m * gen.normal(size=rt.size)
    return one_anchor_dataset("laps", body, anchor, t, rt, r)


def test_an_error_tied_to_a_place_and_repeated_every_lap_widens_the_ellipse_towards_it(rng):
    """Six laps through the same NLOS zone (a quarter of the loop, 0.4 m): the zone pulls the fit 0.1-0.2 m
    horizontally, and the jackknifes over 4 and 16 time stretches see six laps agree (NEES 20-90 for 2 dof).
    Leaving out one cell on every lap at once shows part of the pull: the NEES falls at least by half (by
    4-8 on seeds 0-5; the truth is not always inside: the zone spans 2-3 cells of 12 m, and leaving one out
    leaves the rest). The positions are unchanged and the covariance only widens."""
    ds = laps(int(rng.integers(1 << 30)))
    # the place-to-place term (`jaxcal.trajectory.systematic`) off in both: this test is about the cells
    res = nls.calibrate(ds, {"systematic": False})
    off = nls.calibrate(ds, {"cov_cell_m": 0.0, "cov_cells": 0.0, "systematic": False})
    np.testing.assert_allclose(res.position[0], off.position[0])
    c, c0 = res.covariance[0, :2, :2], off.covariance[0, :2, :2]
    assert np.allclose(c, c.T) and np.linalg.eigvalsh(c - c0).min() > -1e-12
    e = res.position[0, :2] - ds.anchor_truth[0, :2]
    assert e @ np.linalg.solve(c, e) <= 0.5 * e @ np.linalg.solve(c0, e)


def test_a_cell_size_that_means_nothing_is_a_clear_error():
    from jaxcal.errors import JaxcalError

    for bad in (-1.0, float("nan")):
        with pytest.raises(JaxcalError, match="cov_cell_m"):
            nls.calibrate(laps(0), {"cov_cell_m": bad})
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(JaxcalError, match="cov_cells"):
            nls.calibrate(laps(0), {"cov_cells": bad})


def test_route_cells_are_scale_free_and_do_not_depend_on_the_frame(rng):
    """Cells from the route's box (`cov_cells`): the same campaign in another unit of length, shifted and with
    x and y swapped, gets the same cells; a fixed side (`cov_cell_m`) is the grid of `cell_labels`."""
    from types import SimpleNamespace

    ds = laps(int(rng.integers(1 << 30)))
    pos = np.asarray(ds.pose_position)[None, ::3]
    mask = np.ones(pos.shape[:2], bool)
    mask[0, -7:] = False
    k, shift = 0.1 + 10 * rng.random(), rng.normal(size=3) * 100
    moved = pos[..., [1, 0, 2]] * k + shift
    for cells in (2.0, 3.0, 4.0):
        p = SimpleNamespace(cov_cells=cells, cov_cell_m=0.0)
        a, n_a = nls.route_cells(SimpleNamespace(position=pos, mask=mask), p)
        b, n_b = nls.route_cells(SimpleNamespace(position=moved, mask=mask), p)
        # the same partition of the ranges (labels are numbered by first visit, so equal)
        assert n_a == n_b and (a == b).all() and 2 <= n_a <= cells**2
    fixed, _ = nls.route_cells(SimpleNamespace(position=pos, mask=mask), SimpleNamespace(cov_cells=2.0, cov_cell_m=7.0))
    assert (fixed == nls.cell_labels(pos, mask, 7.0)[0]).all()
