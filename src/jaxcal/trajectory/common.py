"""What every trajectory method shares: its settings (`TrajectoryParams`), the linear least-squares
multilateration of one anchor (`multilaterate`: the `ls` method, the start of `nls` and the clock-offset
search of `poses`), the planarity and height-observability checks, and the Result they all build (`finish`).

Linear multilateration: for tag positions p_i and ranges r_i, |p_i - a|^2 = r_i^2 is linear in
(a, c = |a|^2): `-2 p_i . a + c = r_i^2 - |p_i|^2` (positions centred first for conditioning). When the tag
positions of an anchor are (nearly) planar (`is_planar`) the z column is degenerate; then the 2-D problem in
(a_x, a_y, c' = |a_xy|^2 + h^2) is solved and the height above the platform plane is h = sqrt(c' - |a_xy|^2),
placed on the side `side` (+1 = above the tags). The covariance is s^2 (A^T A)^-1 of the linear system
(s^2 = residual variance of the linear equations), propagated to the height by the delta method in the planar
case.

Imports no other trajectory module, so that `poses` (below the methods) can use the multilateration and the
methods can use both without an import circle.
"""

from __future__ import annotations

import logging

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from jaxcal import solver
from jaxcal.data import Result
from jaxcal.errors import JaxcalError
from jaxcal.params import as_dict
from jaxcal.trajectory.pose_error import pose_error_covariances

__all__ = [
    "TrajectoryParams",
    "multilaterate",
    "multilaterate_all",
    "is_planar",
    "height_dop_ratio",
    "unobservable_height",
    "widen_covariance",
    "offset_covariances",
    "report_fits",
    "finish",
]


class TrajectoryParams(eqx.Module):
    """Settings shared by every trajectory method (`ls`, `nls`, `gp`): poses, planarity, clock offset.

    Attributes:
        min_ranges: anchors with fewer valid ranges get no estimate (NaN).
        max_height_dop: an anchor whose tag positions are planar (see below) and whose height dilution of
            precision over its horizontal one exceeds this gets a NaN height (`unobservable_height`).
        planar_tol_m, planar_ratio: an anchor's tag positions count as planar when their z standard
            deviation is below planar_tol_m [m] or below planar_ratio x their horizontal one.
        side: +1 anchors above the platform plane, -1 below (planar case only).
        mirror_z, mirror_min_sep_m: the mirror-image check (`jaxcal.trajectory.mirror`): a fit on the
            other side of the path's plane that converges more than mirror_min_sep_m [m] away is compared
            with the estimate; within mirror_z cluster-robust standard deviations the height is left NaN,
            below -mirror_z the other side replaces the estimate (mirror_z = 0: no check).
        mirror_profile: fits across the path's plane in the mirror-image check's profile (step 4 of
            `jaxcal.trajectory.mirror`: the covariance is widened to hold those that fit within mirror_z,
            and one of them on the other side leaves the height NaN); 0 or 1: no profile.
        systematic: widen every anchor's covariance to the place-to-place part of its range errors taken as one
            error (`jaxcal.trajectory.systematic`: an NLOS excess behind a building repeats on every range from
            there and does not average out); False: the methods' covariances as they are.
        systematic_pool: with `systematic`, each anchor's place-to-place variance is at least the campaign's median
            over its anchors (`systematic.site_variance`): a fit that moves to absorb its own place errors leaves
            residuals that do not show them (twenty-third round); False: each anchor's own.
        pose_sd_m, pose_drift: a stated horizontal pose error (`jaxcal.trajectory.pose_error`): the standard
            deviation [m] per axis of an offset shared by the whole path (frame, lever arm) and the intensity
            [m / sqrt(s)] of a random-walk drift from the first pose (odometry). The ranges cannot show an
            error that moves the tag positions together (the anchor moves with them), so it is added to
            every anchor's covariance by linear propagation through the fit. 0 (default): poses exact (`nls`
            estimates the pose error from the ranges instead: its `estimate_drift`, on by default).
        order, knot_dt_s, max_gap_s: pose B-spline (order 4 = cubic; 0 = automatic).
        time_offset_s, estimate_offset, max_offset_s: pose minus range clock offset [s] and its search.
    """

    min_ranges: int = 10
    max_height_dop: float = 10.0
    planar_tol_m: float = 0.3
    planar_ratio: float = 0.05
    side: float = 1.0
    mirror_z: float = 2.0
    mirror_min_sep_m: float = 0.25
    mirror_profile: int = 17
    systematic: bool = True
    systematic_pool: bool = True
    pose_sd_m: float = 0.0
    pose_drift: float = 0.0
    order: int = 4
    knot_dt_s: float = 0.0
    max_gap_s: float = 0.0
    time_offset_s: float = 0.0
    estimate_offset: bool = False
    max_offset_s: float = 1.0

    def __check_init__(self):
        rules = {  # name -> (holds, what it must be); NaN fails every comparison
            "min_ranges": (self.min_ranges >= 1, "an integer >= 1"),
            "max_height_dop": (self.max_height_dop > 0, "a number > 0"),
            "planar_tol_m": (self.planar_tol_m >= 0, "a number >= 0"),
            "planar_ratio": (self.planar_ratio >= 0, "a number >= 0"),
            "side": (self.side in (1.0, -1.0), "1 or -1"),
            "mirror_z": (self.mirror_z >= 0, "a number >= 0"),
            "mirror_min_sep_m": (self.mirror_min_sep_m >= 0, "a number >= 0"),
            "mirror_profile": (self.mirror_profile >= 0, "an integer >= 0 (0 or 1: no profile)"),
            "pose_sd_m": (self.pose_sd_m >= 0, "a number >= 0 [m]"),
            "pose_drift": (self.pose_drift >= 0, "a number >= 0 [m / sqrt(s)]"),
            "order": (self.order >= 1, "an integer >= 1"),
            "knot_dt_s": (self.knot_dt_s >= 0, "a number >= 0 (0 = automatic)"),
            "max_gap_s": (self.max_gap_s >= 0, "a number >= 0 (0 = automatic)"),
            "max_offset_s": (self.max_offset_s >= 0, "a number >= 0"),
        }
        for name, (holds, want) in rules.items():
            if not holds:
                raise JaxcalError(f"parameter {name}: must be {want}, got {getattr(self, name)}")


def _solve(a_mat, b_vec, mask):
    w = mask.astype(a_mat.dtype)
    ata = (a_mat * w[:, None]).T @ a_mat
    atb = (a_mat * w[:, None]).T @ b_vec
    ridge = 1e-10 * jnp.trace(ata) / ata.shape[0]
    ata_r = ata + ridge * jnp.eye(ata.shape[0])
    x = jnp.linalg.solve(ata_r, atb)
    n = jnp.sum(w)
    res = (a_mat @ x - b_vec) * w
    s2 = jnp.sum(res**2) / jnp.maximum(n - a_mat.shape[1], 1.0)
    return x, s2 * jnp.linalg.inv(ata_r)


def multilaterate(
    pos: Float[Array, "n 3"],
    rng: Float[Array, " n"],
    mask: Bool[Array, " n"],
    planar_tol_m: float = 0.3,
    side: float = 1.0,
    planar_ratio: float = 0.05,
) -> tuple[Float[Array, " 3"], Float[Array, "3 3"]]:
    """Linear LS position [m] and covariance [m^2] of one anchor from (masked) tag positions and ranges."""
    w = mask.astype(pos.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    centre = jnp.sum(pos * w[:, None], axis=0) / n
    q = (pos - centre) * w[:, None]
    zstd = jnp.sqrt(jnp.sum(q[:, 2] ** 2) / n)
    hstd = jnp.sqrt(jnp.sum(q[:, :2] ** 2) / n)
    rhs = rng**2 - jnp.sum(q**2, axis=-1)
    ones = jnp.ones_like(rng)
    # 3-D: unknowns (a, c).
    x3, c3 = _solve(jnp.concatenate([-2.0 * q, ones[:, None]], axis=1), rhs, mask)
    est3, cov3 = x3[:3], c3[:3, :3]
    # Planar: unknowns (a_x, a_y, c'), height from c' - |a_xy|^2.
    x2, c2 = _solve(jnp.stack([-2.0 * q[:, 0], -2.0 * q[:, 1], ones], axis=1), rhs + q[:, 2] ** 2, mask)
    h2 = x2[2] - x2[0] ** 2 - x2[1] ** 2
    h = jnp.sqrt(jnp.maximum(h2, 1e-6))
    g = jnp.array([-x2[0] / h, -x2[1] / h, 0.5 / h])
    est2 = jnp.array([x2[0], x2[1], side * h])
    cov2 = jnp.zeros((3, 3)).at[:2, :2].set(c2[:2, :2])
    cxz = c2[:2, :] @ g
    cov2 = cov2.at[:2, 2].set(cxz).at[2, :2].set(cxz).at[2, 2].set(g @ c2 @ g)
    planar = is_planar(zstd, hstd, planar_tol_m, planar_ratio)
    est = jnp.where(planar, est2, est3) + centre
    cov = jnp.where(planar, cov2, cov3)
    return est, cov


def multilaterate_all(pos, rng, mask, planar_tol_m: float = 0.3, side: float = 1.0, planar_ratio: float = 0.05):
    """`multilaterate` vmapped over anchors: (A, n, 3), (A, n), (A, n) -> (A, 3), (A, 3, 3)."""
    return jax.vmap(lambda p, r, m: multilaterate(p, r, m, planar_tol_m, side, planar_ratio))(pos, rng, mask)


def is_planar(z_std, h_std, planar_tol_m: float, planar_ratio: float):
    """Whether tag positions with these z and horizontal spreads [m] count as planar (z unobservable
    by the linear system): z spread below `planar_tol_m` or below `planar_ratio` x horizontal spread."""
    return (z_std < planar_tol_m) | (z_std < planar_ratio * h_std)


def height_dop_ratio(tag_pos: np.ndarray, anchor: np.ndarray) -> float:
    """sqrt(C_zz / mean(C_xx, C_yy)) of C = (J^T J)^-1, J the rows (unit vector from the tag to the anchor, 1)
    of range-with-bias: how much worse the anchor's height is determined than its horizontal position by
    the geometry alone. From a flat path the height enters the ranges only to second order and trades off
    with the range bias: the ratio grows to tens (measured: 13-39 on the hanyang drives, 3-12 on the hymn
    walks whose tag height varies by 0.5 m)."""
    d = np.asarray(anchor, dtype=float)[None] - np.asarray(tag_pos, dtype=float)
    r = np.linalg.norm(d, axis=1)
    ok = r > 1e-9
    if ok.sum() < 4:
        return float("inf")
    j = np.column_stack([d[ok] / r[ok, None], np.ones(int(ok.sum()))])
    c = np.linalg.pinv(j.T @ j)
    return float(np.sqrt(max(c[2, 2], 0.0) / max(0.5 * (c[0, 0] + c[1, 1]), 1e-300)))


def unobservable_height(groups, est: np.ndarray, p) -> tuple[np.ndarray, np.ndarray]:
    """Anchors whose height the platform's path cannot observe: tag positions planar (`is_planar` with
    `p.planar_tol_m`, `p.planar_ratio`) and a height-to-horizontal DOP ratio (`height_dop_ratio`) above
    `p.max_height_dop`. Returns ((A,) bool, (A,) z spread of the tag positions [m]).

    Not caught here: an anchor fitted on the wrong side of a path that is not flat but nearly planar (a
    gently sloping road), the mirror image through the path's local plane. `finish` checks that next
    (`jaxcal.trajectory.mirror.compare_sides`: a refit from the mirror image and a likelihood-ratio test with
    a cluster-robust variance) and leaves such a height NaN too when the two sides fit alike."""
    pos, mask = np.asarray(groups.position), np.asarray(groups.mask)
    out = np.zeros(est.shape[0], dtype=bool)
    zstd = np.full(est.shape[0], np.nan)
    for a in range(est.shape[0]):
        q = pos[a][mask[a]]
        if q.shape[0] < 4 or not np.isfinite(est[a]).all():
            continue
        zstd[a] = float(np.std(q[:, 2]))
        hstd = float(np.sqrt(np.mean(np.sum((q[:, :2] - q[:, :2].mean(axis=0)) ** 2, axis=1))))
        if bool(is_planar(zstd[a], hstd, p.planar_tol_m, p.planar_ratio)):
            out[a] = height_dop_ratio(q, est[a]) > p.max_height_dop
    return out, zstd


def _axes(unknown) -> str:
    """'x/y' for an (3,) bool of coordinates."""
    return "/".join(n for n, u in zip("xyz", unknown, strict=True) if u)


def widen_covariance(cov: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """(3, 3) covariance `cov` raised, in every direction where it is smaller, to `floor`."""
    cov = 0.5 * (cov + cov.T)
    d = 0.5 * (floor + floor.T) - cov
    lam, vec = np.linalg.eigh(d)
    out = cov + (vec * np.maximum(lam, 0.0)) @ vec.T
    return 0.5 * (out + out.T)


def offset_covariances(info: dict, n_anchors: int) -> np.ndarray:
    """(A, 3, 3) covariance of the anchors from the clock offset's uncertainty: var(tau) s_k s_k^T with
    s_k = d a_k / d tau (`jaxcal.trajectory.offset.OffsetFit.sensitivity`) as `nls.prepare_offset` left
    them in `info` (keys `time_offset_sd_s`, `offset_sensitivity`); zeros where no offset was estimated."""
    sd = info.get("time_offset_sd_s", float("nan"))
    sens = info.get("offset_sensitivity")
    if sens is None or not np.isfinite(sd):
        return np.zeros((n_anchors, 3, 3))
    s = np.asarray(sens, dtype=float)
    return sd**2 * s[:, :, None] * s[:, None, :]


def report_fits(method: str, codes, groups, p, hint: str):
    """The solver outcome (`jaxcal.solver.report`) of the anchors that get a fit (at least `p.min_ranges`
    ranges), with its one warning line naming `method` and `hint` when a fit did not converge."""
    fitted = np.asarray(groups.mask).sum(axis=1) >= p.min_ranges
    rep = solver.report(np.asarray(codes)[fitted], "anchor fits")
    rep.warn(method, hint)
    return rep


def cauchy_weights(res: np.ndarray, min_scale_m: float = 0.05, center: bool = False) -> np.ndarray:
    """Cauchy IRLS weights 1 / (1 + (e / c)^2) of residuals e [m], c = max(2.385 x 1.4826 x median |e|,
    min_scale_m) (the `nls` scale); `center`: median |e - median e| instead (the MAD, for residuals with an offset
    left in them: `jaxcal.trajectory.drift`'s cells). Returns an array shaped like `res`."""
    res = np.asarray(res, dtype=float)
    if res.size == 0:
        return np.ones_like(res)
    dev = res - np.median(res) if center else res
    c = max(2.385 * 1.4826 * float(np.median(np.abs(dev))), min_scale_m)
    return 1.0 / (1.0 + (res / c) ** 2)


def finish(dataset, method, p, groups, est, cov, info, solver=None, pose_cov_extra=None) -> Result:
    """Build the Result: NaN rows for anchors with fewer than `p.min_ranges` ranges or failed fits; a NaN
    height (the rest kept, one warning line) for anchors whose height the path cannot observe
    (`unobservable_height`) and for anchors the ranges cannot tell from their mirror image through the
    path (`jaxcal.trajectory.mirror.compare_sides`, which also moves an anchor to the other side where that
    fits clearly better). With `p.systematic` every covariance is first widened to the place-to-place part of the
    range errors taken as one error (`jaxcal.trajectory.systematic`). A stated pose error (`pose_sd_m`,
    `pose_drift`) is added to every covariance then (`jaxcal.trajectory.pose_error`). `solver` (a
    `jaxcal.solver.SolverReport`) adds `solver_status` and `solver_failed` to the params. `pose_cov_extra`
    ((A, 3, 3) or None): a further pose error covariance, added with the stated one (the shared error `nls`
    estimates, `jaxcal.trajectory.drift`: the part its jackknife cannot see; `gp` adds
    the same)."""
    from jaxcal import __version__

    est = np.array(est, dtype=float)
    cov = np.array(cov, dtype=float)
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    count = np.asarray(groups.mask).sum(axis=1)
    bad = (count < p.min_ranges) | ~np.isfinite(est).all(axis=1) | ~np.isfinite(cov).all(axis=(1, 2))
    est[bad] = np.nan
    cov[bad] = np.nan
    from jaxcal.trajectory.path_shape import line_anchors, shapes

    shape = shapes(groups, p)
    flat, zstd = unobservable_height(groups, est, p)
    flat &= ~(shape.line | shape.steep)  # their heights: the line fit and the side check (`path_shape`)
    if p.systematic:
        from jaxcal.trajectory.systematic import place_variances, site_variance, systematic_covariances

        pool = site_variance(place_variances(groups, est)) if p.systematic_pool else 0.0
        if p.systematic_pool:  # absent where each anchor keeps its own (gp, or systematic_pool=false)
            info = dict(info, systematic_site_sd_m=round(float(np.sqrt(pool)), 4))
        floor = systematic_covariances(groups, est, flat, pool)
        for a in np.flatnonzero(np.isfinite(cov).all(axis=(1, 2))):
            cov[a] = widen_covariance(cov[a], floor[a])
    pose_cov = pose_error_covariances(dataset, groups, est, p, method) + offset_covariances(info, est.shape[0])
    if pose_cov_extra is not None:
        pose_cov = pose_cov + np.where(np.isfinite(est).all(axis=1)[:, None, None], pose_cov_extra, 0.0)
    info = {k: v for k, v in info.items() if k != "offset_sensitivity"}
    cov = cov + pose_cov
    if flat.any():
        est[flat, 2] = np.nan
        cov[flat, 2, :] = np.nan
        cov[flat, :, 2] = np.nan
        names = [dataset.anchor_ids[a] for a in np.flatnonzero(flat)]
        logging.getLogger("jaxcal").warning(
            "%s: the platform path is flat (tag height spread up to %.2f m) for %d anchor(s) (%s): the ranges "
            "do not fix their height; left NaN, horizontal kept; survey the heights or record a path with "
            "height changes (or raise max_height_dop)",
            method,
            float(np.nanmax(zstd[flat])),
            len(names),
            ", ".join(names[:8]) + (", ..." if len(names) > 8 else ""),
        )
    from jaxcal.trajectory.mirror import compare_sides

    sides = compare_sides(groups, est, cov, p, shape)
    est, cov = sides.position, sides.covariance
    refit = sides.moved | sides.restarted  # the covariance of a fit the check made is the fit's alone
    if p.systematic and refit.any():
        floor = systematic_covariances(groups, np.where(refit[:, None], est, np.nan), pool=pool)
        for a in np.flatnonzero(refit):
            cov[a] = widen_covariance(cov[a], floor[a])
    cov[refit] += pose_cov[refit]
    ids = dataset.anchor_ids
    if sides.ambiguous.any():
        amb = np.flatnonzero(sides.ambiguous)
        apart = np.linalg.norm(sides.other[amb] - est[amb], axis=1)
        unknown = sides.unknown[amb]
        for a, u in zip(amb, unknown, strict=True):
            est[a, u] = np.nan
            cov[a, u, :] = np.nan
            cov[a, :, u] = np.nan
        logging.getLogger("jaxcal").warning(
            "%s: the ranges cannot tell %d anchor(s) (%s) from their mirror image through the path "
            "(both sides fit alike: |z| <= %g, %s m apart); left NaN, the rest kept and widened "
            "to both sides; survey them or record a path that climbs and turns near them",
            method,
            amb.size,
            ", ".join(f"{ids[a]} {_axes(u)}" for a, u in zip(amb[:8], unknown[:8], strict=True))
            + (", ..." if amb.size > 8 else ""),
            p.mirror_z,
            "/".join(f"{v:.1f}" for v in apart[:8]),
        )
    lines = line_anchors(groups, est, cov, shape, pose_cov, p)
    if lines:
        logging.getLogger("jaxcal").warning(
            "%s: the path is a straight line (within planar_tol_m = %g m) for %d anchor(s) (%s): the ranges fix "
            "only the position along it and the distance from it, not where on the circle about it; left NaN, "
            "what the circle does not move kept; survey them or record a path that turns near them",
            method,
            p.planar_tol_m,
            len(lines),
            ", ".join(
                f"{ids[a]} {_axes(~np.isfinite(est[a]))} ({v['from_line_m']:.1f} m from the line)"
                for a, v in list(lines.items())[:8]
            )
            + (", ..." if len(lines) > 8 else ""),
        )
    info = dict(
        info,
        unobservable_height=[ids[a] for a in np.flatnonzero(flat)],
        mirror_ambiguous=[ids[a] for a in np.flatnonzero(sides.ambiguous)],
        mirror_moved=[ids[a] for a in np.flatnonzero(sides.moved)],
        mirror_widened=[ids[a] for a in np.flatnonzero(sides.widened)],
        mirror_z={ids[a]: round(float(sides.z[a]), 3) for a in np.flatnonzero(sides.checked)},
        mirror_unknown={ids[a]: _axes(sides.unknown[a]) for a in np.flatnonzero(sides.ambiguous)},
        mirror_restarted=[ids[a] for a in np.flatnonzero(sides.restarted)],
        path_steep=[ids[a] for a in np.flatnonzero(shape.steep)],
        path_line={ids[a]: v for a, v in lines.items()},
    )
    params = as_dict(p)
    params.update({f"info_{k}": v for k, v in info.items()})
    if solver is not None:
        params.update(solver.params())
    return Result(
        ids=dataset.anchor_ids,
        position=est,
        method=method,
        dataset=dataset.name,
        frame="world",
        params=params,
        covariance=cov,
        software=f"jaxcal {__version__}",
    )
