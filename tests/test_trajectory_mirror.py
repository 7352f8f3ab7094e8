"""The mirror-image check of trajectory anchors (`jaxcal.trajectory.mirror`, applied by `common.finish`)."""

import numpy as np
import pytest

from jaxcal.trajectory import mirror, nls
from trajectory_campaigns import one_anchor_dataset


def sloped_campaign(seed=0, bumps_m=0.0, noise_m=0.05, height_m=1.5, stretch_m=0.0, zone_m=0.0):
    """A platform on a loop over a plane sloping 15 % (plus bumps of `bumps_m`), one anchor 1.5 m above
    the plane beside the loop. Without bumps the mirror image through the plane gives the same ranges
    (the path is not flat: its height spread of 0.6 m passes `is_planar`); with bumps of a metre it does
    not. (Bumps of 2 cm under 5 cm of independent noise already tell the sides apart at about 2 sd.)
    `height_m`: the anchor's height above the plane; `stretch_m`: sd of a range error that is constant over
    each of 20 stretches of the recording (an NLOS state that persists while the platform passes); `zone_m`: a
    range error on every pass through one place (x > 3 m)."""
    gen = np.random.default_rng(seed)
    anchor = np.array([[2.0, 6.5, 0.15 * 2.0 + height_m]])

    def body(t):
        x, y = 6 * np.cos(0.2 * t), 5 * np.sin(0.4 * t)
        return np.stack([x, y, 0.15 * x + bumps_m * np.sin(0.9 * t)], 1), 0.2 * t

    t = np.arange(0, 80.0, 0.1)
    rt = np.arange(0.5, 79.5, 0.05)
    pr, _ = body(rt)
    r = np.linalg.norm(pr - anchor[0], axis=1) + 0.1 + noise_m * gen.normal(size=rt.size)
    r += np.repeat(stretch_m * gen.normal(size=20), -(-rt.size // 20))[: rt.size]
    if zone_m:  # an error tied to a place: every range taken with the tag at x > 3 m, on every pass
        r += zone_m * (pr[:, 0] > 3.0)
    return one_anchor_dataset("sloped", body, anchor, t, rt, r)


@pytest.mark.parametrize("seed", [0, 1])
def test_mirror_ambiguous_height_is_nan_with_one_warning_line(seed, caplog):
    ds = sloped_campaign(seed)
    with caplog.at_level("WARNING", logger="jaxcal"):
        res = nls.calibrate(ds)
    assert np.isnan(res.position[0, 2]) and np.isnan(res.covariance[0, 2]).all()
    # the mirror through a 15 % slope is 0.44 m off horizontally: the ellipse is widened to both sides
    assert np.linalg.norm(res.position[0, :2] - ds.anchor_truth[0, :2]) < 0.6
    assert np.sqrt(np.linalg.eigvalsh(res.covariance[0, :2, :2]).max()) > 0.2
    assert res.params["info_mirror_ambiguous"] == ["a0"] and res.params["info_unobservable_height"] == []
    lines = [r.getMessage() for r in caplog.records if "mirror" in r.getMessage()]
    assert len(lines) == 1 and "(a0 z)" in lines[0] and "\n" not in lines[0]


@pytest.mark.parametrize("seed", [0, 1])
def test_height_kept_where_the_path_climbs(seed):
    ds = sloped_campaign(seed, bumps_m=1.5)
    res = nls.calibrate(ds)
    assert res.params["info_mirror_ambiguous"] == [] and res.params["info_mirror_moved"] == []
    assert np.linalg.norm(res.position[0] - ds.anchor_truth[0]) < 0.1


def test_mirror_check_off_keeps_the_height():
    res = nls.calibrate(sloped_campaign(0), {"mirror_z": 0.0})
    assert np.isfinite(res.position[0]).all() and res.params["info_mirror_ambiguous"] == []


def test_profile_widens_the_covariance_to_hold_what_fits_as_well(rng):
    """An anchor 0.4 m above a bumpy sloped path, with range errors that persist over stretches: the
    height is poorly fixed and the cost is not quadratic in it. The profile across the plane (mirror step 4)
    only widens the covariance, and a height it keeps has a 3-D ellipse that holds the truth. (Where the
    height is left NaN the horizontal error can still exceed its ellipse: the stretch errors shift the
    radial position, which is nls's covariance, not the profile's, 1 of 20 seeds.)"""
    from scipy.stats import chi2

    ds = sloped_campaign(int(rng.integers(1 << 30)), bumps_m=0.3, height_m=0.4, stretch_m=0.1)
    res = nls.calibrate(ds)
    ref = nls.calibrate(ds, {"mirror_profile": 0})
    np.testing.assert_allclose(res.position[0, :2], ref.position[0, :2])
    assert np.linalg.eigvalsh(res.covariance[0, :2, :2] - ref.covariance[0, :2, :2]).min() > -1e-12
    e = res.position[0] - ds.anchor_truth[0]
    if np.isfinite(e).all():
        assert e @ np.linalg.solve(res.covariance[0], e) <= chi2.ppf(0.95, 3)
        np.testing.assert_allclose(res.position[0], ref.position[0])
        assert np.linalg.eigvalsh(res.covariance[0] - ref.covariance[0]).min() > -1e-12
    else:
        assert res.params["info_mirror_ambiguous"] == ["a0"]


def test_nan_height_horizontal_ellipse_holds_the_fit_at_every_height_near_the_plane(rng, monkeypatch):
    """Where the mirror check leaves the height NaN, the horizontal fit depends on the height the ranges cannot
    tell (on a 15 % slope the mirror is 0.44 m off horizontally). Slow reference: explicit SciPy refits of
    the in-plane position and bias at fixed distances u from the path's plane (Cauchy loss at the check's
    scale), at heights between the profile's grid points; each one's horizontal position lies inside the
    reported 95 % ellipse (mirror step 5), and the covariance stays symmetric PSD. The envelope takes the
    inner span's fits only (the `mirror_profile` fits to |u0| + 1 m), not the outer ones that reach as far
    as the covariance (tenth round)."""
    from scipy.optimize import least_squares
    from scipy.stats import chi2

    calls = []
    envelope = mirror.height_envelope
    monkeypatch.setattr(mirror, "height_envelope", lambda d: calls.append(np.array(d)) or envelope(d))
    ds = sloped_campaign(int(rng.integers(1 << 30)), noise_m=0.05 + 0.1 * rng.random())
    res = nls.calibrate(ds)
    assert len(calls) == 1 and 0 < calls[0].shape[0] <= nls.NLSParams().mirror_profile
    assert res.params["info_mirror_ambiguous"] == ["a0"] and np.isnan(res.position[0, 2])
    cov = res.covariance[0, :2, :2]
    assert np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov).min() > 0
    groups, _ = nls.prepare_offset(ds, nls.NLSParams())  # as nls.calibrate (clock offset applied)
    m = np.asarray(groups.mask[0])
    pos, r = np.asarray(groups.position[0])[m], np.asarray(groups.range[0])[m]
    centre, n = (np.asarray(v) for v in mirror.local_plane(pos, r, np.ones(r.size, bool)))
    e1 = np.cross(n, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    est = np.append(res.position[0, :2], 0.0)
    est[2] = centre[2] - ((est[:2] - centre[:2]) @ n[:2]) / n[2]  # the estimate's foot on the plane
    b0 = np.median(r - np.linalg.norm(pos - est, axis=1))
    scale = max(2.385 * 1.4826 * np.median(np.abs(r - np.linalg.norm(pos - est, axis=1) - b0)), 0.05)
    q95 = chi2.ppf(0.95, 2)
    for u in np.linspace(-0.97, 0.97, 12):  # |u| <= 1 m lies in the profile's span; not its grid points

        def anchor(y, u=u):
            return centre + u * n + y[0] * e1 + y[1] * e2

        def residual(y, u=u):
            return np.linalg.norm(pos - anchor(y, u), axis=1) + y[2] - r

        y0 = [(est - centre) @ e1, (est - centre) @ e2, b0]
        fit = least_squares(residual, y0, loss="cauchy", f_scale=scale, xtol=1e-10, ftol=1e-10)
        d = anchor(fit.x)[:2] - res.position[0, :2]
        assert d @ np.linalg.solve(cov, d) <= q95, (u, d)


def test_padded_mapped_side_check_equals_the_vmapped_one(rng):
    """The side check's programs run on anchors padded to `anchor_bucket` rows, one anchor after the other
    (`mirror._map_valid`: `lax.map`, padding rows skipped). Reference: the plain vmap over the real anchors (the
    code before the fifteenth round), here of the profile across the plane (the costly one; `_compare_all` maps
    the same way): equal to rounding (1e-6 relative: batched and single arithmetic differ in the last bits); 3
    anchors in a bucket of 4."""
    import functools

    import jax
    import jax.numpy as jnp

    assert [mirror.anchor_bucket(k) for k in (1, 2, 3, 5, 8, 9)] == [1, 2, 4, 8, 8, 16]
    t = np.arange(0.0, 60.0, 0.1)
    pos = np.stack([6 * np.cos(0.2 * t), 5 * np.sin(0.4 * t), 0.9 * np.cos(0.2 * t)], 1)
    anchors = np.array([[2.0, 6.5, 2.0], [-4.0, 1.0, 0.8], [1.0, -7.0, 3.0]]) + rng.normal(0, 0.3, (3, 3))
    rng_m = np.linalg.norm(pos[None] - anchors[:, None], axis=2) + 0.1 + 0.05 * rng.normal(size=(3, t.size))
    mask = np.ones((3, t.size), bool)
    mask[1, -100:] = False
    cells = np.where(mask, (pos[None, :, 0] > 0).astype(np.int64), 2)
    centre = np.zeros((3, 3))
    normal = np.tile(np.array([-0.15, 0.0, 1.0]) / np.hypot(0.15, 1.0), (3, 1))
    x0 = np.concatenate([anchors + 0.05, np.full((3, 1), 0.1)], 1)
    args = (np.broadcast_to(pos, (3, *pos.shape)), rng_m, mask, x0, np.full(3, 0.2), centre, normal, np.full(3, 0.3))
    args = (*args, cells)
    k, valid = mirror._padded(3)
    assert k.size == 4 and valid.tolist() == [True, True, True, False]
    got = mirror._profile_all(tuple(jnp.asarray(v)[k] for v in args), jnp.asarray(valid), 16, 100, 5, 2)
    one = functools.partial(mirror._profile_one, n_clusters=16, max_steps=100, n_grid=5, n_cells=2)
    ref = jax.vmap(one)(*(jnp.asarray(v) for v in args))
    for g, r in zip(got, ref, strict=True):
        assert np.asarray(g).shape[0] == 4 and not np.asarray(g)[3].any()  # the padding row: skipped, zeros
        np.testing.assert_allclose(np.asarray(g)[:3], np.asarray(r), rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("u_plane", [0.0, -1e-12, 1e-12])
def test_a_profile_fit_on_the_plane_counts_as_the_other_side_whatever_its_rounded_sign(monkeypatch, u_plane):
    """Step 4's side rule: a plausible fit on the path's plane (z <= mirror_z, far from the estimate) leaves the
    height NaN, as every fit just past the plane fits as well. The grid's point u = 0 comes out of the solver at
    +-1e-12 or 0; its rounded sign decided the anchor's height on small clean seed 4 (twentieth round)."""
    from types import SimpleNamespace

    p = SimpleNamespace(mirror_z=2.0, mirror_profile=3, mirror_min_sep_m=0.3, side=1.0, n_clusters=16)
    est = np.array([[0.0, 0.0, -0.9]])  # 0.9 m below the plane z = 0
    pts = np.array([[[0.0, 0.0, -1.8], [0.1, 0.0, u_plane], [0.2, 0.0, 0.9]]])
    zk = np.array([[[5.0, 5.0], [1.5, 1.5], [3.5, 3.5]]])  # only the fit on the plane is plausible
    codes = np.zeros((1, 3), dtype=int)
    monkeypatch.setattr(mirror, "_profile_all", lambda *a, **k: (pts, zk, codes))
    out = mirror.SideCheck(
        checked=np.zeros(1, bool),
        ambiguous=np.zeros(1, bool),
        moved=np.zeros(1, bool),
        z=np.full(1, np.nan),
        other=np.full((1, 3), np.nan),
        position=est.copy(),
        covariance=np.eye(3)[None] * 0.01,
        widened=np.zeros(1, bool),
        unknown=np.zeros((1, 3), bool),
        restarted=np.zeros(1, bool),
    )
    data = (np.zeros((1, 4, 3)), np.ones((1, 4)), np.ones((1, 4), bool), np.zeros((1, 4), int), 1)
    fit = (np.zeros((1, 4)), np.ones(1), np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))
    mirror._apply_profile(out, np.array([0]), (np.zeros(1, bool), np.zeros(1, bool)), data, fit, p)
    assert out.ambiguous[0] and out.z[0] == 1.5
    np.testing.assert_allclose(out.other[0], pts[0, 1])
    # a plausible fit on the estimate's own side, short of the plane, decides nothing
    pts[0, 1, 2] = -0.05
    out.ambiguous[0] = False
    mirror._apply_profile(out, np.array([0]), (np.zeros(1, bool), np.zeros(1, bool)), data, fit, p)
    assert not out.ambiguous[0]
