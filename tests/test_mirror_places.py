"""The mirror check and errors tied to a place (`jaxcal.trajectory.mirror` with nls's route cells): the side
test's variance counts an error repeated on every pass once, the covariance holds every fit across the path's
plane that this test cannot reject, and the side is decided from the fit alone, not from its covariance."""

import numpy as np
from scipy.stats import chi2

from jaxcal.trajectory import mirror, nls
from test_trajectory_mirror import sloped_campaign


def _z_reference(diff, mask, n_stretches, cells):
    """Slow reference of `mirror._vuong_z`: the sum of `diff` over its sandwich sd, the variance the larger of
    that over consecutive stretches and that over the non-empty cells."""
    d = diff[mask]
    n = d.size
    stretch = np.arange(n) * n_stretches // n
    sums = np.array([d[stretch == g].sum() for g in range(n_stretches)])
    var_t = n_stretches / (n_stretches - 1) * np.sum((sums - d.sum() / n_stretches) ** 2)
    used = np.unique(cells[mask])
    sums_c = np.array([d[cells[mask] == c].sum() for c in used])
    var_c = used.size / (used.size - 1) * np.sum((sums_c - d.sum() / used.size) ** 2)
    return d.sum() / np.sqrt(var_t + 1), d.sum() / np.sqrt(max(var_t, var_c) + 1)


def test_side_test_variance_over_route_cells_equals_the_explicit_sums(rng):
    n, g = 400, 9
    res0 = rng.normal(size=n) * 0.1
    cells = rng.integers(0, g - 1, n)  # cell g - 1 empty
    res = res0 + rng.normal(size=g)[cells] * 0.2 + 0.05  # an error shared by the entries of each cell
    mask = np.ones(n, bool)
    mask[-30:] = False
    cells[-30:] = g
    z_time, z_place = (float(v) for v in mirror._vuong_z(res, res0, mask, 0.2, 16, cells, g))
    diff = np.log1p((res / 0.2) ** 2) - np.log1p((res0 / 0.2) ** 2)
    np.testing.assert_allclose([z_time, z_place], _z_reference(diff, mask, 16, cells), rtol=1e-9)
    assert abs(z_place) <= abs(z_time) + 1e-12


def test_every_fit_across_the_plane_the_side_test_cannot_reject_lies_in_the_ellipsoid(rng):
    """A bumpy sloped path with an error on every pass through one place (0.3 m): slow reference = explicit
    SciPy refits of the in-plane position and bias at fixed distances u from the path's plane (Cauchy loss at
    the check's scale), scored against the estimate by the place-and-time clustered z (`_z_reference`); each
    one the test cannot reject (z <= mirror_z) lies inside the reported 95 % ellipsoid (3-D where the height
    is kept, its horizontal part where it is NaN)."""
    from scipy.optimize import least_squares

    ds = sloped_campaign(int(rng.integers(1 << 30)), bumps_m=0.3, height_m=0.8, zone_m=0.3)
    res = nls.calibrate(ds)
    p = nls.NLSParams()
    groups, _ = nls.prepare_offset(ds, p)  # the groups nls.calibrate fits (clock offset applied)
    m = np.asarray(groups.mask[0])
    pos, r = np.asarray(groups.position[0])[m], np.asarray(groups.range[0])[m]
    cells = nls.route_cells(groups, p)[0][0][m]
    (est, _, bias, _), _, _ = nls.solve_all_checked(groups, p)
    x0 = np.append(np.asarray(est[0]), float(bias[0]))
    if res.params["info_mirror_moved"]:
        x0[:3] = res.position[0]  # the profile is taken about the fit that replaced the estimate
        x0[3] = np.median(r - np.linalg.norm(pos - x0[:3], axis=1))
    res0 = np.linalg.norm(pos - x0[:3], axis=1) + x0[3] - r
    scale = max(2.385 * 1.4826 * np.median(np.abs(res0 - np.median(res0))), 0.05)
    centre, n = (np.asarray(v) for v in mirror.local_plane(pos, r, np.ones(r.size, bool)))
    e1 = np.cross(n, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    fin = np.isfinite(res.position[0])
    cov = res.covariance[0][np.ix_(fin, fin)]
    assert np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov).min() > 0
    u0 = (x0[:3] - centre) @ n
    tested = 0
    for u in np.linspace(-abs(u0) - 0.97, abs(u0) + 0.97, 11):  # within the profile's inner span

        def anchor(y, u=u):
            return centre + u * n + y[0] * e1 + y[1] * e2

        def residual(y, u=u):
            return np.linalg.norm(pos - anchor(y, u), axis=1) + y[2] - r

        y0 = [(x0[:3] - centre) @ e1, (x0[:3] - centre) @ e2, x0[3]]
        fit = least_squares(residual, y0, loss="cauchy", f_scale=scale, xtol=1e-10, ftol=1e-10)
        diff = np.log1p((residual(fit.x) / scale) ** 2) - np.log1p((res0 / scale) ** 2)
        if _z_reference(diff, np.ones(r.size, bool), 16, cells)[1] > p.mirror_z:
            continue
        tested += 1
        d = (anchor(fit.x) - res.position[0])[fin]
        assert d @ np.linalg.solve(cov, d) <= chi2.ppf(0.95, int(fin.sum())), (u, d, res.params["info_mirror_z"])
    assert tested >= 1


def test_the_side_is_decided_by_the_fit_not_by_its_covariance(rng):
    """The profile's inner span comes from the fit alone: the same fit with a covariance 30 times wider gets the
    same decision (NaN height, moved or kept), whatever the covariance does to the profile's outer points."""
    seed = int(rng.integers(1 << 30))
    for ds in (sloped_campaign(seed), sloped_campaign(seed, bumps_m=0.3, height_m=0.5, stretch_m=0.1)):
        p = nls.NLSParams()
        groups, _ = nls.prepare_offset(ds, p)  # the groups nls.calibrate fits (clock offset applied)
        (est, cov, _, _), _, _ = nls.solve_all_checked(groups, p)
        a = mirror.compare_sides(groups, np.asarray(est), np.asarray(cov), p)
        b = mirror.compare_sides(groups, np.asarray(est), 30.0 * np.asarray(cov), p)
        assert (a.ambiguous == b.ambiguous).all() and (a.moved == b.moved).all()
        np.testing.assert_allclose(a.position, b.position)


def test_the_place_clustered_z_cannot_reject_a_difference_that_one_cell_holds(rng):
    """Why the profile (mirror step 4) widens a kept height over its whole span when few route cells hold the
    evidence (docs/benchmarks/uncertainty.md, seventeenth round): a log-likelihood difference D that lies in one
    cell has the cell sandwich variance G / (G - 1) (D^2 (1 - 1/G)^2 + (G - 1) D^2 / G^2) = D^2 exactly, so the
    place-clustered z is at most D / sqrt(D^2 + 1) < 1 however large D is, while the same difference spread over
    time stretches is significant."""
    n, g = 600, 6
    res0 = rng.normal(size=n) * 0.1
    cells = rng.integers(0, g, n)  # each cell visited throughout the recording (every pass)
    mask = np.ones(n, bool)
    for shift in (0.1, 0.3, 1.0):
        res = res0 + shift * (cells == 0)  # a misfit in one place only
        z_time, z_place = (float(v) for v in mirror._vuong_z(res, res0, mask, 0.1, 16, cells, g))
        diff = np.log1p((res / 0.1) ** 2) - np.log1p((res0 / 0.1) ** 2)
        d = diff.sum()
        assert d > 0 and 0 < z_place <= d / np.sqrt(d**2 + 1.0) * (1 + 1e-9) < 1
        if shift >= 0.3:
            assert z_time > nls.NLSParams().mirror_z
