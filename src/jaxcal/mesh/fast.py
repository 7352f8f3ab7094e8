"""Windowed kernels of the fast PGP path (`likelihood="window"`, the default; see `pgp`).

Once every node is localised its posterior is concentrated. The motion update of eq. (7)-(8) only
reads the `top_k` most probable cells, and every factor of eq. (11) is at most 1 (log <= 0), so the
log posterior of a cell outside a square window of W x W cells around those cells is bounded by the
Gaussian tail of the motion kernel:

    log p(g) <= logsumexp_m [log p_m - relu(d_m - v dt)^2 / (2 sigma_v^2)] - log Z_window,

with d_m the distance from source cell m to the nearest cell outside the window and Z_window the
normaliser over the window. When that bound times the node's number of cells is below
`WINDOW_LOG_TOL` (e^-30 ~ 1e-13 of the mass) for every node, and the previous epoch's
bound was too, the epoch is evaluated on the windows only (W^2 cells per node instead of the whole
grid) and equals the full evaluation up to rounding; otherwise the filter runs that epoch on the
full grid (the direct evaluation) and re-centres the windows. No other approximation is made: the
same top-k cells, hypotheses, factors, normalisation and estimate, on fewer cells.

Window cells are indexed like the grid (`ix`-major), so ties in `lax.top_k` resolve as on the full
grid. Everything here is for one node; `pgp` vmaps it.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from jaxcal.mesh import grid as G

__all__ = [
    "WINDOW_LOG_TOL",
    "window_side",
    "window_origin",
    "window_cells",
    "extract_window",
    "scatter_window",
    "predict_window",
    "outside_bound",
    "window_mask",
    "RING_SPAN",
    "ring_loglik",
    "ring_loglik_loop",
    "ring_loglik_grid",
]

# log of the largest total posterior mass that may lie outside a node's window in a windowed epoch
WINDOW_LOG_TOL = -30.0
# the next epoch tries the small window only when this epoch's small-window bound is this many nats
# below WINDOW_LOG_TOL (a try that fails is re-run on the big window: twice the work)
SMALL_WINDOW_MARGIN = 4.0
# S of `ring_loglik`: a neighbour's kept hypotheses must lie in an S x S block of cells
RING_SPAN = 5
# `ring_loglik` sums eq. (11)'s kernel in linear space; a factor below this could have lost
# precision to underflow (float64's smallest normal number is ~2.2e-308), so it is not used
RING_MIN_FACTOR = 1e-280


def window_side(window_m: float, grid: G.Grid) -> int:
    """Static window side W [cells] for a window of `window_m` metres; 0 when it would cover the
    grid (the window path is then the full path)."""
    w = int(math.ceil(window_m / grid.cell_m - 1e-9))
    w = max(w, 3)
    return 0 if w >= grid.n_side else w


def window_origin(flat_idx: Int[Array, ""], n_side: int, w: int) -> Int[Array, " 2"]:
    """(ix0, iy0) of the W x W window centred on cell `flat_idx` (grid flat index), clamped to the
    grid."""
    ix, iy = flat_idx // n_side, flat_idx % n_side
    o = jnp.stack([ix, iy]) - w // 2
    return jnp.clip(o, 0, n_side - w).astype(jnp.int32)


def window_cells(org: Int[Array, " 2"], grid: G.Grid, w: int, dtype) -> Float[Array, "cells 2"]:
    """(W^2, 2) centres [m] of the window cells, flat index `a * W + b` for grid cell
    `(ix0 + a, iy0 + b)`."""
    a = jnp.arange(w, dtype=dtype)
    ax = (org[0].astype(dtype) + a - grid.n_half) * grid.cell_m
    ay = (org[1].astype(dtype) + a - grid.n_half) * grid.cell_m
    gx, gy = jnp.meshgrid(ax, ay, indexing="ij")
    return jnp.stack([gx.ravel(), gy.ravel()], axis=-1)


def extract_window(
    logp: Float[Array, "nx ny"], w: int
) -> tuple[Float[Array, "w w"], Int[Array, " 2"], Float[Array, ""]]:
    """Window of one node's full-grid log posterior around its MLE cell.

    Returns:
        (W, W) window log values (not renormalised), (2,) origin, and the largest log value outside
        the window (`-inf` when there is none).
    """
    n = logp.shape[0]
    org = window_origin(jnp.argmax(logp.ravel()), n, w)
    win = jax.lax.dynamic_slice(logp, (org[0], org[1]), (w, w))
    i = jnp.arange(n)
    inx = (i >= org[0]) & (i < org[0] + w)
    iny = (i >= org[1]) & (i < org[1] + w)
    out = jnp.max(jnp.where(inx[:, None] & iny[None, :], -jnp.inf, logp))
    return win, org, out


def scatter_window(win: Float[Array, "w w"], org: Int[Array, " 2"], n_side: int) -> Float[Array, "n n"]:
    """Full-grid log posterior with the window's values and `-inf` elsewhere."""
    full = jnp.full((n_side, n_side), -jnp.inf, win.dtype)
    return jax.lax.dynamic_update_slice(full, win, (org[0], org[1]))


def predict_window(
    vals: Float[Array, " k"],
    src: Float[Array, "k 2"],
    cells: Float[Array, "cells 2"],
    step_m: Float[Array, ""],
    sigma_v: Float[Array, ""],
) -> Float[Array, " cells"]:
    """Motion update eq. (7)-(8) from K sources (log weights `vals`, positions `src`) onto the
    square window `cells` (ix-major): the same arithmetic as `grid.predict_static` (v dt = 0,
    separable) or `grid.predict_direct` (any v dt), with targets other than the sources' grid."""
    n = int(round(math.sqrt(cells.shape[0])))

    def static():
        ax = cells[::n, 0]
        ay = cells[:n, 1]
        bx = -0.5 * jnp.square((ax[:, None] - src[None, :, 0]) / sigma_v)
        by = -0.5 * jnp.square((ay[:, None] - src[None, :, 1]) / sigma_v)
        vmax = jnp.max(vals)
        wts = jnp.where(jnp.isfinite(vals), jnp.exp(vals - vmax), 0.0)
        mx = jnp.max(bx, axis=1)
        my = jnp.max(by, axis=1)
        s = (jnp.exp(bx - mx[:, None]) * wts[None, :]) @ jnp.exp(by - my[:, None]).T
        tiny = jnp.finfo(s.dtype).tiny
        return (jnp.log(jnp.maximum(s, tiny)) + vmax + mx[:, None] + my[None, :]).reshape(-1)

    def direct():
        d = G.safe_norm(jnp.stack([cells[None, :, 0] - src[:, 0, None], cells[None, :, 1] - src[:, 1, None]], axis=-1))
        logt = -0.5 * jnp.square((d - step_m) / sigma_v)
        return jax.nn.logsumexp(vals[:, None] + logt, axis=0)

    return jax.lax.cond(step_m == 0, static, direct)


def outside_bound(
    vals: Float[Array, " k"],
    src_idx: Int[Array, "k 2"],
    org: Int[Array, " 2"],
    n_side: int,
    w: int,
    cell_m: float,
    step_m: Float[Array, ""],
    sigma_v: Float[Array, ""],
) -> Float[Array, ""]:
    """Upper bound on the (unnormalised) log prior of eq. (7)-(8) at any cell outside the window.

    Args:
        vals: (K,) log weights of the sources. src_idx: (K, 2) their grid indices (ix, iy).
        org: (2,) window origin. n_side, w, cell_m: grid side, window side [cells], cell size [m].
        step_m, sigma_v: as in `grid.predict`.

    Returns:
        `logsumexp_m [vals_m - relu(d_m - step)^2 / (2 sigma_v^2)]` with `d_m` a lower bound on the
        distance from source m to the nearest grid cell outside the window [m] (`-inf` when the
        window is the whole grid).
    """
    big = jnp.asarray(jnp.inf, vals.dtype)
    lo = jnp.where(org > 0, (src_idx - org + 1).astype(vals.dtype), big)  # to cell org - 1
    hi = jnp.where(org + w < n_side, (org + w - src_idx).astype(vals.dtype), big)  # to org + w
    d = jnp.min(jnp.minimum(lo, hi), axis=-1) * cell_m
    gap = jnp.maximum(d - step_m, 0.0)
    t = jnp.where(jnp.isfinite(gap), -0.5 * jnp.square(gap / sigma_v), -jnp.inf)
    return jax.nn.logsumexp(jnp.where(jnp.isfinite(vals), vals + t, -jnp.inf))


def window_mask(mask: Bool[Array, "nx ny"], org: Int[Array, " 2"], w: int) -> Bool[Array, " cells"]:
    """(W^2,) allowed cells of one node inside its window."""
    return jax.lax.dynamic_slice(mask, (org[0], org[1]), (w, w)).reshape(-1)


def _ring_factor(
    org: Int[Array, " 2"],
    w: int,
    grid: G.Grid,
    hyp_pos: Float[Array, "hyp 2"],
    hyp_logw: Float[Array, " hyp"],
    sigma: Float[Array, ""],
    z: Float[Array, ""],
    p_out: Float[Array, ""],
    nlos,
    span: int,
) -> tuple[Float[Array, "w w"], Bool[Array, ""]]:
    """One pair of `ring_loglik`: the floored factor `(1 - p_out) f + p_out` on the window, and
    whether it is exact (hypotheses within the S x S block, no factor below `RING_MIN_FACTOR`)."""
    dtype = hyp_logw.dtype
    s = span
    hidx = jnp.round(hyp_pos / grid.cell_m).astype(jnp.int32) + grid.n_half  # (H, 2)
    kept = jnp.isfinite(hyp_logw)
    big = jnp.iinfo(jnp.int32).max
    corner = jnp.min(jnp.where(kept[:, None], hidx, big), axis=0)  # (2,)
    off = jnp.where(kept[:, None], hidx - corner[None, :], 0)  # (H, 2), >= 0
    fits = jnp.all(jnp.where(kept[:, None], off < s, True))
    wts = jnp.where(kept, jnp.exp(hyp_logw), 0.0)
    # (S, S) weight image of the block (hypotheses outside it only matter when `fits` fails)
    oh = jnp.arange(s)
    img = jnp.einsum(
        "h,ha,hb->ab",
        wts,
        (off[:, 0, None] == oh).astype(dtype),
        (off[:, 1, None] == oh).astype(dtype),
    )
    # kernel image R[u, v] at offsets (org - corner - (S - 1) + (u, v)) cells from the block corner
    u = jnp.arange(w + s - 1)
    o = org - corner - (s - 1)
    dx = ((o[0] + u) * grid.cell_m).astype(dtype)
    dy = ((o[1] + u) * grid.cell_m).astype(dtype)
    d = G.safe_norm(jnp.stack(jnp.broadcast_arrays(dx[:, None], dy[None, :]), axis=-1))
    r = jnp.exp(G.range_kernel_log(z - d, sigma, nlos))
    # hypothesis at block offset (a, b) reads R[p + S - 1 - a, q + S - 1 - b] for window cell (p, q)
    f = jnp.zeros((w, w), dtype)
    for a in range(s):
        for b in range(s):
            f = f + img[a, b] * r[s - 1 - a : s - 1 - a + w, s - 1 - b : s - 1 - b + w]
    fac = (1.0 - p_out) * f + p_out
    return fac, fits & (jnp.min(fac) > RING_MIN_FACTOR)


def ring_loglik(
    org: Int[Array, " 2"],
    w: int,
    grid: G.Grid,
    hyp_pos: Float[Array, "nodes hyp 2"],
    hyp_logw: Float[Array, "nodes hyp"],
    hyp_sigma: Float[Array, " nodes"],
    z_i: Float[Array, " nodes"],
    use_i: Bool[Array, " nodes"],
    p_out: Float[Array, ""],
    nlos=None,
    span: int = RING_SPAN,
) -> tuple[Float[Array, " cells"], Bool[Array, ""]]:
    """`grid.node_loglik` on the W x W window at `org`, with one kernel image per neighbour.

    Window cells and hypotheses (eq. 10) are grid cells, so the distance from a cell to a
    hypothesis is a whole number of cells along each axis. When neighbour j's kept hypotheses lie
    in an S x S block, the range kernel of eq. (11) (`grid.range_kernel_log`) is evaluated once on
    the (W + S - 1)^2 offsets from that block and the factor is the weighted sum of S^2 shifted
    copies of that image (most with weight 0): (W + S - 1)^2 kernel evaluations instead of
    W^2 x H, and no transcendental in the sum. The sum is in linear space; the log is taken once
    per (cell, neighbour).

    Args:
        org: (2,) window origin (grid indices). w: W (static). grid: the grid.
        hyp_pos, hyp_logw: (N, H, 2) hypothesis positions [m] (grid cell centres), (N, H)
            normalised log weights (-inf: not kept). hyp_sigma: (N,) range std [m].
        z_i: (N,) ranges [m] (NaN missing). use_i: (N,) neighbours that contribute.
        p_out, nlos: as in `grid.pair_loglik`. span: S (static).

    Returns:
        ((W^2,) log likelihood, ix-major like `window_cells`; ok). `ok` is False when a used
        neighbour's hypotheses do not fit in S x S cells or a factor fell below
        `RING_MIN_FACTOR` (linear-space underflow): the caller then uses `grid.node_loglik`.
    """
    zs = jnp.where(use_i, z_i, 0.0)
    fac, ok = jax.vmap(_ring_factor, in_axes=(None, None, None, 0, 0, 0, 0, None, None, None))(
        org, w, grid, hyp_pos, hyp_logw, hyp_sigma, zs, p_out, nlos, span
    )
    ll = jnp.where(use_i[:, None, None], jnp.log(jnp.maximum(fac, RING_MIN_FACTOR)), 0.0)
    return jnp.sum(ll, axis=0).reshape(-1), jnp.all(ok | ~use_i)


def ring_loglik_loop(
    org: Int[Array, " 2"],
    w: int,
    grid: G.Grid,
    hyp_pos: Float[Array, "nodes hyp 2"],
    hyp_logw: Float[Array, "nodes hyp"],
    hyp_sigma: Float[Array, " nodes"],
    z_i: Float[Array, " nodes"],
    use_i: Bool[Array, " nodes"],
    p_out: Float[Array, ""],
    nlos=None,
    span: int = RING_SPAN,
    remat: bool = False,
) -> Float[Array, " cells"]:
    """`ring_loglik` (same arguments, same values) as a loop over the neighbours that skips those
    without a range; a pair whose image is not exact is evaluated by `grid.pair_loglik` on the
    window's cells. Cost ~ used pairs, for large windows with few used neighbours. Not to be
    `vmap`ped (a batched `cond` runs both branches). `remat`: as in `grid.node_loglik_sparse`."""
    n = hyp_logw.shape[0]
    dtype = hyp_logw.dtype

    def neighbour(j, acc):
        def add(acc):
            fac, ok = _ring_factor(org, w, grid, hyp_pos[j], hyp_logw[j], hyp_sigma[j], z_i[j], p_out, nlos, span)

            def direct():
                cells = window_cells(org, grid, w, dtype)
                ll = G.pair_loglik(cells, hyp_pos[j], hyp_logw[j], z_i[j], hyp_sigma[j], p_out, nlos)
                return ll.reshape(w, w)

            return acc + jax.lax.cond(ok, lambda: jnp.log(fac), direct)

        return jax.lax.cond(use_i[j], jax.checkpoint(add) if remat else add, lambda a: a, acc)

    return jax.lax.fori_loop(0, n, neighbour, jnp.zeros((w, w), dtype)).reshape(-1)


def ring_loglik_grid(
    grid: G.Grid,
    hyp_pos: Float[Array, "nodes hyp 2"],
    hyp_logw: Float[Array, "nodes hyp"],
    hyp_sigma: Float[Array, " nodes"],
    z_i: Float[Array, " nodes"],
    use_i: Bool[Array, " nodes"],
    p_out: Float[Array, ""],
    nlos=None,
    span: int = RING_SPAN,
    remat: bool = False,
) -> Float[Array, " cells"]:
    """`grid.node_loglik_sparse` on the whole grid, by `ring_loglik`'s kernel images: a loop over
    neighbours skipping those without a range; a pair whose image is not exact (see
    `ring_loglik`) is evaluated by `grid.pair_loglik`. Same arguments (but the grid for the cells),
    same result up to rounding; not to be `vmap`ped (see `node_loglik_sparse`). `remat`: as in
    `node_loglik_sparse`."""
    org = jnp.zeros((2,), jnp.int32)
    return ring_loglik_loop(org, grid.n_side, grid, hyp_pos, hyp_logw, hyp_sigma, z_i, use_i, p_out, nlos, span, remat)
