"""The anchor frame of a mesh configuration, and rigid alignment.

Frame of (a0, a1, a2) (CONTRACT 1.1): a0 at the origin, a1 on the positive x axis, a2 in the half plane
y > 0. For 3-D points a2 lies in the x-y plane with y > 0 and z completes a right-handed frame.

Pure NumPy: these run once per evaluation, outside any traced code.
"""

from __future__ import annotations

import numpy as np

from jaxcal.errors import InputError

__all__ = ["to_frame", "to_frame_track", "frame_covariance", "align_rigid", "apply_rigid"]


def to_frame(points: np.ndarray, a0: int, a1: int, a2: int) -> np.ndarray:
    """Express points in the frame defined by three of them.

    Args:
        points: (N, D) positions [m], D = 2 or 3, in any frame. Rows a0, a1, a2 must be finite and
            not collinear; other rows may be NaN (they stay NaN).
        a0, a1, a2: row indices defining the frame.

    Returns:
        (N, D) positions in the anchor frame.
    """
    p = np.asarray(points, dtype=np.float64)
    d = p.shape[1]
    if d not in (2, 3):
        raise InputError(f"points must be (N, 2) or (N, 3), got {p.shape}")
    o = p[a0]
    ex = p[a1] - o
    nx = np.linalg.norm(ex)
    if not np.isfinite(nx) or nx == 0:
        raise InputError(f"frame undefined: a0 (row {a0}) and a1 (row {a1}) coincide or are unknown")
    ex = ex / nx
    v2 = p[a2] - o
    if d == 2:
        ey = np.array([-ex[1], ex[0]])
        if v2 @ ey < 0:
            ey = -ey
        if abs(v2 @ ey) < 1e-12:
            raise InputError("frame undefined: a0, a1, a2 are collinear")
        rot = np.stack([ex, ey])  # rows: new axes
    else:
        ey = v2 - (v2 @ ex) * ex
        ny = np.linalg.norm(ey)
        if not np.isfinite(ny) or ny < 1e-12:
            raise InputError("frame undefined: a0, a1, a2 are collinear or unknown")
        ey = ey / ny
        ez = np.cross(ex, ey)
        rot = np.stack([ex, ey, ez])
    return (p - o) @ rot.T


def align_rigid(est: np.ndarray, truth: np.ndarray, reflection: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Best rigid motion (rotation, translation, optionally reflection; no scale) taking `est` onto `truth`.

    Least squares over the rows where both are finite (Kabsch / Umeyama without scale).

    Args:
        est: (N, D) estimated positions. truth: (N, D) reference positions.
        reflection: allow an improper rotation (det = -1), as for mirror-ambiguous mesh solutions.

    Returns:
        (R, t) with `est @ R.T + t` closest to `truth`; R is (D, D), t is (D,).
    """
    est = np.asarray(est, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    ok = np.isfinite(est).all(axis=1) & np.isfinite(truth).all(axis=1)
    d = est.shape[1]
    if ok.sum() < 2:
        return np.eye(d), np.zeros(d)
    x, y = est[ok], truth[ok]
    mx, my = x.mean(axis=0), y.mean(axis=0)
    h = (x - mx).T @ (y - my)
    u, _, vt = np.linalg.svd(h)
    r = vt.T @ u.T
    if not reflection and np.linalg.det(r) < 0:
        vt[-1] *= -1
        r = vt.T @ u.T
    return r, my - r @ mx


def apply_rigid(points: np.ndarray, r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """`points @ r.T + t` (NaN rows stay NaN)."""
    return np.asarray(points, dtype=np.float64) @ r.T + t


def to_frame_track(track: np.ndarray, a0: int, a1: int, a2: int) -> np.ndarray:
    """`to_frame` for every epoch of a 2-D track at once, each epoch in the frame of its own estimates.

    Args:
        track: (K, N, 2) positions [m] in any frame, NaN where a node has no estimate.
        a0, a1, a2: row indices defining the frame.

    Returns:
        (K, N, 2) positions in the anchor frame; a whole epoch is NaN where a0, a1 or a2 has no
        estimate, a0 and a1 coincide or a2 lies on the a0-a1 line.
    """
    p = np.asarray(track, dtype=np.float64)
    o = p[:, a0]
    v = p[:, a1] - o
    nv = np.linalg.norm(v, axis=1)
    ok = np.isfinite(nv) & (nv > 0)
    ex = v / np.where(ok, nv, 1.0)[:, None]
    ey = np.stack([-ex[:, 1], ex[:, 0]], axis=1)
    s = np.sign(np.einsum("kd,kd->k", p[:, a2] - o, ey))
    ok &= np.isfinite(s) & (s != 0)
    ey = ey * np.where(ok, s, 1.0)[:, None]
    u = p - o[:, None]
    out = np.stack([np.einsum("knd,kd->kn", u, ex), np.einsum("knd,kd->kn", u, ey)], axis=-1)
    out[~ok] = np.nan
    return out


def frame_covariance(points: np.ndarray, cov: np.ndarray, a0: int, a1: int, a2: int) -> np.ndarray:
    """First-order covariance of `to_frame(points, a0, a1, a2)` (2-D) from independent node covariances.

    With u = p_i - p_a0, v = p_a1 - p_a0 (length L), the frame's rotation R (rows e_x, e_y = s perp(e_x))
    and y = R u: dy = R du + c (perp(e_x) . dv) / L with c = (s y_y, -s y_x). The node's own, a0's and
    a1's covariances enter through their Jacobians (a2 only picks the sign s). Cross-covariances between
    nodes are not known to the filters that call this and are left out.

    Args:
        points: (N, 2) positions [m] in the source frame. cov: (N, 2, 2) their covariances [m^2].
        a0, a1, a2: the frame's rows.

    Returns:
        (N, 2, 2) covariances in the anchor frame (0 for a0; a1's y variance 0); NaN rows stay NaN.
    """
    p = np.asarray(points, dtype=np.float64)
    c_in = np.asarray(cov, dtype=np.float64)
    y = to_frame(p, a0, a1, a2)
    v = p[a1] - p[a0]
    length = np.linalg.norm(v)
    ex = v / length
    eperp = np.array([-ex[1], ex[0]])
    s = 1.0 if (p[a2] - p[a0]) @ eperp > 0 else -1.0
    rot = np.stack([ex, s * eperp])
    out = np.full_like(c_in, np.nan)
    for i in range(p.shape[0]):
        if i == a0:
            out[i] = 0.0
            continue
        c = np.array([s * y[i, 1], -s * y[i, 0]])
        g = np.outer(c, eperp) / length  # d y_i / d p_a1
        if i == a1:
            a = rot + g
            tot = a @ c_in[i] @ a.T
        else:
            tot = rot @ c_in[i] @ rot.T + g @ c_in[a1] @ g.T
        b = rot + g  # d y_i / d p_a0 is -(R + g)
        tot = tot + b @ c_in[a0] @ b.T
        out[i] = 0.5 * (tot + tot.T)
    out[a1, 1, :] = out[a1, :, 1] = 0.0
    return out
