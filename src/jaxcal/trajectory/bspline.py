"""Cumulative uniform B-splines of order N (degree N - 1) for position streams (paper 001, Sec. III-B).

A spline segment `i` covers `[t0 + i dt, t0 + (i + 1) dt)`; with `u = (t - t0) / dt - i` in [0, 1) the
position is, in the cumulative form of the paper,

    p(t) = c_i + sum_{j=1}^{N-1} lambda_j(u) (c_{i+j} - c_{i+j-1}),   lambda = M~ [1, u, ..., u^{N-1}],

with `M~` the cumulative blending matrix (`cumulative_blending_matrix`). The control points `c` are
*fitted* to the pose stream by least squares (not the poses themselves used as control points): a
spline of order N then reproduces every polynomial of degree N - 1 exactly, so interpolation adds no
smoothing bias on smooth motion. The normal equations are banded (bandwidth N) and solved with a
banded Cholesky factorisation (host-side, once per dataset). A small penalty on the N-th differences of
the control points keeps the system regular where a knot interval holds fewer poses than it needs; it
vanishes on polynomials of degree N - 1, so it does not bias them.

Streams with gaps (`max_gap_s`) are split into independent pieces (`fit_pieces`); times outside every
piece evaluate to NaN, and callers drop them.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxcal.errors import InputError

__all__ = [
    "blending_matrix",
    "cumulative_blending_matrix",
    "SplinePieces",
    "fit_pieces",
    "evaluate",
]


def blending_matrix(order: int) -> np.ndarray:
    """Uniform B-spline blending matrix `M` (order x order): weights = M @ [1, u, ..., u^(order-1)].

    Row j holds the polynomial coefficients (ascending powers of u) of the weight of control point
    `i + j` on segment `i` (Qin's closed form, as in Sommer et al., 2020).
    """
    k = order
    m = np.zeros((k, k))
    for j in range(k):  # control point
        for n in range(k):  # power of u
            s = sum((-1) ** (q - j) * math.comb(k, q - j) * (k - 1 - q) ** (k - 1 - n) for q in range(j, k))
            m[j, n] = math.comb(k - 1, n) * s / math.factorial(k - 1)
    return m


def cumulative_blending_matrix(order: int) -> np.ndarray:
    """Cumulative blending matrix `M~`: row j = sum of rows j..N-1 of `blending_matrix` (row 0 = [1, 0, ...])."""
    m = blending_matrix(order)
    return np.cumsum(m[::-1], axis=0)[::-1].copy()


class SplinePieces(eqx.Module):
    """Fitted cumulative B-spline pieces of one D-dimensional stream.

    Attributes:
        control: (C, D) control points of all pieces, concatenated [m].
        offset: (S,) int index of each piece's first control point in `control`.
        t0: (S,) start time of each piece [s]; t1: (S,) its end time [s].
        dt: (S,) knot spacing of each piece [s]. n_seg: (S,) number of segments of each piece.
        order: spline order N (static).
    """

    control: Float[Array, "c d"]
    offset: Array
    t0: Float[Array, " s"]
    t1: Float[Array, " s"]
    dt: Float[Array, " s"]
    n_seg: Array
    order: int = eqx.field(static=True)


def _banded_cholesky_solve(ab: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve A X = RHS for symmetric positive definite banded A (lower form ab[k, i] = A[i + k, i]).

    Plain O(n b^2) loops: run once per dataset on the host (n = number of control points).
    """
    b, n = ab.shape[0] - 1, ab.shape[1]
    fac = np.zeros_like(ab)  # fac[k, i] = L[i + k, i]
    for i in range(n):
        s = ab[0, i]
        for m in range(max(0, i - b), i):
            s -= fac[i - m, m] ** 2
        if s <= 0:
            raise np.linalg.LinAlgError("banded Cholesky: matrix not positive definite")
        fac[0, i] = math.sqrt(s)
        for k in range(1, min(b, n - 1 - i) + 1):
            r = i + k
            s = ab[k, i]
            for m in range(max(0, r - b), i):
                s -= fac[r - m, m] * fac[i - m, m]
            fac[k, i] = s / fac[0, i]
    y = np.array(rhs, dtype=float)
    for i in range(n):  # forward: L Y = RHS
        for m in range(max(0, i - b), i):
            y[i] -= fac[i - m, m] * y[m]
        y[i] /= fac[0, i]
    for i in range(n - 1, -1, -1):  # backward: L^T X = Y
        for r in range(i + 1, min(n, i + b + 1)):
            y[i] -= fac[r - i, i] * y[r]
        y[i] /= fac[0, i]
    return y


def _fit_one_piece(t: np.ndarray, x: np.ndarray, dt: float, order: int, penalty: float):
    k = order
    n_seg = max(1, int(math.ceil((t[-1] - t[0]) / dt - 1e-9)))
    n_ctrl = n_seg + k - 1
    seg, u = _segment(t, t[0], dt, n_seg)
    w = np.power(u[:, None], np.arange(k)[None, :]) @ blending_matrix(k).T  # (P, k) weights
    # Normal equations A^T A in banded lower form.
    ab = np.zeros((k + 1, n_ctrl))  # bandwidth k: the N-th difference spans N + 1 control points
    rhs = np.zeros((n_ctrl, x.shape[1]))
    for a in range(k):
        np.add.at(rhs, seg + a, w[:, a : a + 1] * x)
        for c in range(a, k):
            np.add.at(ab[c - a], seg + a, w[:, a] * w[:, c])
    # Penalty on N-th differences of the control points (zero on degree N-1 polynomials), scaled to
    # the data term so that it only matters where the data leave the system under-determined.
    scale = penalty * max(ab[0].mean(), 1e-12)
    dk = np.array([(-1) ** (k - j) * math.comb(k, j) for j in range(k + 1)], dtype=float)
    n_rows = n_ctrl - k  # difference rows r cover control points r .. r + k
    if n_rows > 0:
        for a in range(k + 1):
            for c in range(a, k + 1):
                ab[c - a, a : a + n_rows] += scale * dk[a] * dk[c]
    ab[0] += 1e-12 * max(ab[0].max(), 1e-12)  # round-off guard only
    ctrl = _banded_cholesky_solve(ab, rhs)
    return ctrl, n_seg


def _segment(t, t0, dt, n_seg):
    s = (np.asarray(t) - t0) / dt
    seg = np.clip(np.floor(s).astype(np.int64), 0, n_seg - 1)
    return seg, s - seg


def fit_pieces(
    time_s: np.ndarray,
    values: np.ndarray,
    order: int = 4,
    knot_dt_s: float = 0.0,
    max_gap_s: float = 0.0,
    penalty: float = 1e-6,
) -> SplinePieces:
    """Fit cumulative uniform B-spline pieces to a sampled stream (host side, once per dataset).

    Args:
        time_s: (P,) strictly increasing sample times [s].
        values: (P, D) samples (e.g. positions [m]).
        order: spline order N >= 2 (4 = cubic).
        knot_dt_s: knot spacing [s]; 0 = the median sample interval.
        max_gap_s: the stream is split where consecutive samples are further apart; 0 = 5 x knot spacing.
        penalty: weight of the N-th difference regulariser relative to the data term.

    Returns:
        SplinePieces; each piece spans its samples' time range.
    """
    t = np.asarray(time_s, dtype=float)
    x = np.asarray(values, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    if order < 2:
        raise InputError(f"B-spline order must be >= 2, got {order}")
    dts = np.diff(t)
    dt = float(knot_dt_s) if knot_dt_s > 0 else float(np.median(dts)) if dts.size else 1.0
    gap = float(max_gap_s) if max_gap_s > 0 else 5.0 * dt
    cuts = np.concatenate([[0], np.nonzero(dts > gap)[0] + 1, [t.size]])
    ctrl, off, t0, t1, dtl, nseg = [], [], [], [], [], []
    n = 0
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        tp, xp = t[a:b], x[a:b]
        if tp.size == 1:  # a lone sample: a constant piece of zero length
            c, ns = np.repeat(xp, order, axis=0), 1
        else:
            c, ns = _fit_one_piece(tp, xp, dt, order, penalty)
        ctrl.append(c)
        off.append(n)
        n += c.shape[0]
        t0.append(tp[0])
        t1.append(tp[-1])
        dtl.append(dt)
        nseg.append(ns)
    return SplinePieces(
        control=jnp.asarray(np.concatenate(ctrl)),
        offset=jnp.asarray(np.array(off)),
        t0=jnp.asarray(np.array(t0)),
        t1=jnp.asarray(np.array(t1)),
        dt=jnp.asarray(np.array(dtl)),
        n_seg=jnp.asarray(np.array(nseg)),
        order=order,
    )


def evaluate(spline: SplinePieces, time_s: Float[Array, " r"]) -> Float[Array, "r d"]:
    """Evaluate the spline at times [s] (traceable); NaN outside every piece's [t0, t1].

    Args:
        spline: fitted pieces.
        time_s: (R,) query times [s].

    Returns:
        (R, D) values, cumulative form of Sec. III-B.
    """
    k = spline.order
    mc = jnp.asarray(cumulative_blending_matrix(k))
    t = jnp.asarray(time_s)
    piece = jnp.clip(jnp.searchsorted(spline.t0, t, side="right") - 1, 0, spline.t0.shape[0] - 1)
    t0, t1, dt, ns = spline.t0[piece], spline.t1[piece], spline.dt[piece], spline.n_seg[piece]
    s = (t - t0) / dt
    seg = jnp.clip(jnp.floor(s).astype(jnp.int32), 0, ns - 1)
    u = s - seg
    lam = jnp.power(u[:, None], jnp.arange(k)[None, :]) @ mc.T  # (R, k)
    base = spline.offset[piece] + seg
    idx = base[:, None] + jnp.arange(k)[None, :]
    c = spline.control[idx]  # (R, k, D)
    diffs = c[:, 1:] - c[:, :-1]
    p = c[:, 0] + jnp.einsum("rj,rjd->rd", lam[:, 1:], diffs)
    inside = (t >= t0) & (t <= t1)
    return jnp.where(inside[:, None], p, jnp.nan)
