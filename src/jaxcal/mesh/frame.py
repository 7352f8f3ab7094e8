"""The anchor frame of a mesh configuration, and rigid alignment.

Frame of (a0, a1, a2) (CONTRACT 1.1): a0 at the origin, a1 on the positive x axis, a2 in the half plane
y > 0. For 3-D points a2 lies in the x-y plane with y > 0 and z completes a right-handed frame.

Pure NumPy: these run once per evaluation, outside any traced code.
"""

from __future__ import annotations

import numpy as np

__all__ = ["to_frame", "align_rigid", "apply_rigid"]


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
        raise ValueError(f"points must be (N, 2) or (N, 3), got {p.shape}")
    o = p[a0]
    ex = p[a1] - o
    nx = np.linalg.norm(ex)
    if not np.isfinite(nx) or nx == 0:
        raise ValueError(f"frame undefined: a0 (row {a0}) and a1 (row {a1}) coincide or are unknown")
    ex = ex / nx
    v2 = p[a2] - o
    if d == 2:
        ey = np.array([-ex[1], ex[0]])
        if v2 @ ey < 0:
            ey = -ey
        if abs(v2 @ ey) < 1e-12:
            raise ValueError("frame undefined: a0, a1, a2 are collinear")
        rot = np.stack([ex, ey])  # rows: new axes
    else:
        ey = v2 - (v2 @ ex) * ex
        ny = np.linalg.norm(ey)
        if not np.isfinite(ny) or ny < 1e-12:
            raise ValueError("frame undefined: a0, a1, a2 are collinear or unknown")
        ey = ey / ny
        ez = np.cross(ex, ey)
        rot = np.stack([ex, ey, ez])
    return (p - o) @ rot.T


def align_rigid(
    est: np.ndarray, truth: np.ndarray, reflection: bool = True
) -> tuple[np.ndarray, np.ndarray]:
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
