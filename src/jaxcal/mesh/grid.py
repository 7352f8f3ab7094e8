"""Grid machinery of the grid-based Bayesian self-calibration filter (paper 000, Section III).

One square grid of cell centres `(x, y) = ((ix - c) * cell_m, (iy - c) * cell_m)` for
`ix, iy = 0 .. 2c`, shared by every node, so that the posteriors of all nodes are one batched array
of
shape `(nodes, nx, ny)` with `nx = ny = 2c + 1`; the origin (a0) is the centre cell. Per-node
regions are
log-masks on that grid (eq. 5-6):

- a0: the origin cell only (no uncertainty, Section III-A1);
- a1: the cells on the positive x axis, `iy = c, ix >= c`: this row *is* the 1-D histogram of eq.
(5)
  over `[0, d_max]` with `d_max = c * cell_m` and bins of `cell_m` (the 2-D motion and likelihood
  restricted to the row reduce exactly to the 1-D ones);
- a2: the half plane `y >= 0` (eq. 6); every other node: the whole grid.

Extent rule (`extent_radius`): the half-width R is the largest shortest-path distance from a0
through
the graph of per-pair median ranges (so every node a chain of ranges can place is covered, and a few
outliers do not blow the grid up), plus `margin_m`, capped by `extent_m`.

The per-item kernels here (one node, one pair) are plain functions; the filter in `pgp` vmaps
them.
`node_loglik` is the one hot function (eq. 11); a faster implementation (FFT ring convolution,
windows)
can replace it behind the same signature.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

__all__ = [
    "Grid",
    "extent_radius",
    "make_grid",
    "region_masks",
    "safe_norm",
    "top_hypotheses",
    "soft_hypotheses",
    "predict",
    "pair_loglik",
    "node_loglik",
    "node_loglik_sparse",
    "predict_direct",
    "predict_static",
    "window_estimate",
    "mean_cov",
]


class Grid(eqx.Module):
    """Square grid `[-c, c]^2 * cell_m` of cell centres (static: its shape is compile-time).

    Attributes:
        n_half: c, cells on each side of the origin; the grid has `(2c + 1)^2` cells.
        cell_m: cell size [m].
    """

    n_half: int = eqx.field(static=True)
    cell_m: float = eqx.field(static=True)

    @property
    def n_side(self) -> int:
        return 2 * self.n_half + 1

    @property
    def n_cells(self) -> int:
        return self.n_side * self.n_side

    def axis(self, dtype=None) -> Float[Array, " n"]:
        """(n,) cell-centre coordinates along one axis [m]."""
        return (
            # canonicalize: a float64 request without x64 is float32, silently (no UserWarning)
            jnp.arange(self.n_side, dtype=jax.dtypes.canonicalize_dtype(dtype or float)) - self.n_half
        ) * self.cell_m

    def cells(self, dtype=None) -> Float[Array, "cells 2"]:
        """(nx * ny, 2) cell centres [m], flat index `ix * ny + iy`."""
        a = self.axis(dtype)
        gx, gy = jnp.meshgrid(a, a, indexing="ij")
        return jnp.stack([gx.ravel(), gy.ravel()], axis=-1)


def make_grid(radius_m: float, cell_m: float) -> Grid:
    """The smallest grid of cells `cell_m` whose half-width is at least `radius_m`."""
    return Grid(n_half=max(1, int(math.ceil(radius_m / cell_m - 1e-9))), cell_m=float(cell_m))


def extent_radius(ranges: np.ndarray, a0: int, margin_m: float, cap_m: float) -> float:
    """Half-width R [m] of the square grid (host NumPy; runs once per dataset).

    Args:
        ranges: (K, N, N) symmetric ranges [m], NaN missing.
        a0: index of the origin node.
        margin_m: added to the farthest shortest-path distance.
        cap_m: upper bound on R (`extent_m`).

    Returns:
        R = min(cap_m, max_i shortest_path(a0 -> i) + margin_m) over the graph of per-pair median
        ranges; `cap_m` when no node is reachable.
    """
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(ranges, axis=0) if ranges.shape[0] else np.full(ranges.shape[1:], np.nan)
    n = ranges.shape[1]
    dist = np.where(np.isfinite(med), med, np.inf)
    np.fill_diagonal(dist, 0.0)
    for k in range(n):  # Floyd-Warshall: N is small (tens of nodes)
        dist = np.minimum(dist, dist[:, k : k + 1] + dist[k : k + 1, :])
    reach = dist[a0][np.isfinite(dist[a0])]
    if reach.size <= 1:
        return float(cap_m)
    return float(min(cap_m, reach.max() + margin_m))


def region_masks(grid: Grid, n_nodes: int) -> Bool[np.ndarray, "nodes nx ny"]:
    """(N, nx, ny) allowed cells per node (order a0, a1, a2, others); see the module doc."""
    c, n = grid.n_half, grid.n_side
    m = np.ones((n_nodes, n, n), dtype=bool)
    m[0] = False
    m[0, c, c] = True
    m[1] = False
    m[1, c:, c] = True
    m[2, :, :c] = False
    return m


def safe_norm(v: Float[Array, "... 2"]) -> Float[Array, ...]:
    """Euclidean norm over the last axis with a finite gradient at zero."""
    d2 = jnp.sum(v * v, axis=-1)
    pos = d2 > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)


def _safe_sqrt(d2):
    pos = d2 > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)


def top_k(x: Float[Array, " n"], k: int) -> tuple[Float[Array, " k"], Int[Array, " k"]]:
    """`lax.top_k(x, k)` (same values, same indices, ties to the lower index), faster on CPU.

    XLA's CPU top-k is much faster in float32 than in float64. Rounding to float32 is monotonic,
    so the float64 top k lie among the 2k largest float32 values unless more than k + 1 values
    share the float32 value of the k-th (then the lower indices are kept, as for exact ties); the
    exact float64 top k are then ranked among those 2k candidates.
    """
    n = x.shape[-1]
    if x.dtype == jnp.float32 or n <= 2 * k:
        return jax.lax.top_k(x, k)
    m = 2 * k
    _, cand = jax.lax.top_k(x.astype(jnp.float32), m)
    cand = jnp.sort(cand)
    xc = x[cand]
    # rank of each candidate (0: largest; ties to the lower index) by (2k)^2 comparisons, which
    # is cheaper than a float64 sort on CPU; then place each candidate at its rank
    i = jnp.arange(m)
    before = (xc[None, :] > xc[:, None]) | ((xc[None, :] == xc[:, None]) & (i[None, :] < i[:, None]))
    rank = jnp.sum(before, axis=1)
    j = jnp.zeros((m,), i.dtype).at[rank].set(i)[:k]
    return xc[j], cand[j]


def top_hypotheses(
    logp: Float[Array, " cells"], cells: Float[Array, "cells 2"], n_hyp: int, tau: Float[Array, ""]
) -> tuple[Float[Array, "hyp 2"], Float[Array, " hyp"]]:
    """Position hypotheses of one node, eq. (10): its most probable cells up to mass `tau`.

    Cells are taken in order of decreasing probability while the mass taken *before* a cell is below
    `tau` (so the set is the smallest reaching `tau`), at most `n_hyp` of them; weights are
    renormalised
    over the set.

    Args:
        logp: (C,) normalised log posterior. cells: (C, 2) cell centres [m].
        n_hyp: cap on the number of hypotheses (static). tau: mass fraction in (0, 1].

    Returns:
        (H, 2) hypothesis positions [m] and (H,) log weights (-inf for cells not taken).
    """
    vals, idx = top_k(logp, n_hyp)
    w = jnp.exp(vals)
    before = jnp.concatenate([jnp.zeros((1,), w.dtype), jnp.cumsum(w)[:-1]])
    keep = (before < tau) & jnp.isfinite(vals)
    keep = keep.at[0].set(True)
    lw = jnp.where(keep, vals, -jnp.inf)
    return cells[idx], lw - jax.nn.logsumexp(lw)


def soft_hypotheses(
    logp: Float[Array, " cells"],
    cells: Float[Array, "cells 2"],
    n_hyp: int,
    tau: Float[Array, ""],
    temp: Float[Array, ""],
) -> tuple[Float[Array, "hyp 2"], Float[Array, " hyp"]]:
    """`top_hypotheses` with a smooth cut (differentiable in `tau`), for gradient tuning.

    Cell l of the sorted cells gets the log weight `log p_l + log sigmoid((tau - m_l) / temp)`, with
    `m_l` the mass of the cells before it (the hard rule keeps l iff `m_l < tau`); the most probable
    cell is always kept whole. As `temp -> 0` this is `top_hypotheses` (except at `m_l == tau`).

    Args:
        logp, cells, n_hyp, tau: as in `top_hypotheses`. temp: temperature of the cut (mass units).

    Returns:
        (H, 2) hypothesis positions [m] and (H,) normalised log weights.
    """
    vals, idx = top_k(logp, n_hyp)
    w = jnp.where(jnp.isfinite(vals), jnp.exp(vals), 0.0)
    before = jnp.concatenate([jnp.zeros((1,), w.dtype), jnp.cumsum(w)[:-1]])
    cut = jax.nn.log_sigmoid((tau - before) / temp).at[0].set(0.0)
    lw = jnp.where(jnp.isfinite(vals), vals + cut, -jnp.inf)
    return cells[idx], lw - jax.nn.logsumexp(lw)


def predict(
    logp: Float[Array, " cells"],
    cells: Float[Array, "cells 2"],
    top_k: int,
    step_m: Float[Array, ""],
    sigma_v: Float[Array, ""],
) -> Float[Array, " cells"]:
    """Motion update of one node, eq. (7)-(8), over its `top_k` most probable cells (log space).

    `log pbar(g_i) = logsumexp_{m in K} [log p_m - (|g_i - g_m| - v dt)^2 / (2 sigma_v^2)]`; the
    Gaussian's constant is dropped (it cancels in the normalisation of eq. 12). For `v dt = 0` the
    kernel is separable in x and y and the sum is one small matrix product (`predict_static`), else
    it
    is evaluated directly (`predict_direct`).

    Args:
        logp: (C,) log posterior of the previous epoch. cells: (C, 2) [m].
        top_k: K of eq. (7) (static). step_m: v * dt [m]. sigma_v: transition std [m].

    Returns:
        (C,) unnormalised log prior.
    """
    return jax.lax.cond(
        step_m == 0,
        lambda: predict_static(logp, cells, top_k, sigma_v),
        lambda: predict_direct(logp, cells, top_k, step_m, sigma_v),
    )


def predict_direct(logp, cells, k: int, step_m, sigma_v):
    """Eq. (7)-(8) evaluated directly: (C, K) transition terms, any `v dt`."""
    vals, idx = top_k(logp, k)
    src = cells[idx]
    d = safe_norm(jnp.stack([cells[None, :, 0] - src[:, 0, None], cells[None, :, 1] - src[:, 1, None]], axis=-1))
    logt = -0.5 * jnp.square((d - step_m) / sigma_v)
    return jax.nn.logsumexp(vals[:, None] + logt, axis=0)


def predict_static(logp, cells, k: int, sigma_v):
    """Eq. (7)-(8) for `v dt = 0`: `exp(-|d|^2 / 2s^2) = exp(-dx^2 / 2s^2) exp(-dy^2 / 2s^2)`, so
    the sum over
    the K sources is `Ex diag(p) Ey^T`, with each row and column shifted by its largest log term so
    the
    product stays in range. Where even that underflows (cells whose prior is below ~1e-30 of the
    bound), the bound times the smallest normal number is used: finite, and negligible."""
    n = int(round(math.sqrt(cells.shape[0])))
    vals, idx = top_k(logp, k)
    src = cells[idx]
    ax = cells[::n, 0]  # x of row ix (cells are ix-major)
    ay = cells[:n, 1]
    bx = -0.5 * jnp.square((ax[:, None] - src[None, :, 0]) / sigma_v)  # (nx, K)
    by = -0.5 * jnp.square((ay[:, None] - src[None, :, 1]) / sigma_v)  # (ny, K)
    vmax = jnp.max(vals)
    w = jnp.where(jnp.isfinite(vals), jnp.exp(vals - vmax), 0.0)
    mx = jnp.max(bx, axis=1)
    my = jnp.max(by, axis=1)
    s = (jnp.exp(bx - mx[:, None]) * w[None, :]) @ jnp.exp(by - my[:, None]).T  # (nx, ny)
    tiny = jnp.finfo(s.dtype).tiny
    out = jnp.log(jnp.maximum(s, tiny)) + vmax + mx[:, None] + my[None, :]
    return out.reshape(-1)


def pair_loglik(
    cells: Float[Array, "cells 2"],
    hyp_pos: Float[Array, "hyp 2"],
    hyp_logw: Float[Array, " hyp"],
    z: Float[Array, ""],
    sigma: Float[Array, ""],
    p_out: Float[Array, ""],
    nlos: tuple[Float[Array, ""], Float[Array, ""]] | None = None,
) -> Float[Array, " cells"]:
    """Log of one factor of eq. (11): `log sum_l w_l exp(-(|g - g_l| - z)^2 / (2 sigma^2))` at
    every cell.

    With `p_out > 0` the factor is mixed with a constant floor, `(1 - p_out) * factor + p_out` (a
    robust
    option for outlier ranges; `p_out = 0` is the paper's eq. 11).

    With `nlos = (w, mean_m)` the Gaussian kernel is replaced by the NLOS-aware mixture of
    `range_kernel_log` (skewed towards long ranges); `None` is the paper's Gaussian.

    Args:
        cells: (C, 2) [m]. hyp_pos: (H, 2) [m]. hyp_logw: (H,) normalised log weights.
        z: measured range [m]. sigma: range std [m]. p_out: floor weight in [0, 1).
        nlos: optional (NLOS weight in [0, 1), NLOS mean excess [m]).

    Returns:
        (C,) log likelihood.
    """
    # (H, C) layout: the reductions run over the short hypothesis axis with cells contiguous.
    dx = cells[None, :, 0] - hyp_pos[:, 0, None]
    dy = cells[None, :, 1] - hyp_pos[:, 1, None]
    d = _safe_sqrt(dx * dx + dy * dy)
    ll = jax.nn.logsumexp(hyp_logw[:, None] + range_kernel_log(z - d, sigma, nlos), axis=0)
    return jnp.logaddexp(jnp.log1p(-p_out) + ll, jnp.log(p_out))


def range_kernel_log(
    e: Float[Array, "*s"],
    sigma: Float[Array, ""],
    nlos: tuple[Float[Array, ""], Float[Array, ""]] | None = None,
) -> Float[Array, "*s"]:
    """Log of the range kernel of eq. (11) at range errors `e = z - |g - g_l|` [m].

    Gaussian (`nlos=None`, the paper): `-e^2 / (2 sigma^2)` (peak 1, no normalising constant).
    Mixture (`nlos = (w, mean_m)`): `(1 - w) exp(-e^2 / 2 sigma^2) + w sigma sqrt(2 pi) EMG(e)`,
    EMG = the LOS Gaussian convolved with a positive exponential of mean `mean_m` (NLOS ranges
    are long, never short). Both are the density of `e` times `sigma sqrt(2 pi)`, so they
    integrate to the same constant and `tune.neg_log_predictive` holds for either; `w = 0` is the
    Gaussian exactly.
    """
    q = -0.5 * jnp.square(e * (1.0 / sigma))
    if nlos is None:
        return q
    w, mean_m = nlos
    lam = 1.0 / mean_m
    ls = lam * sigma
    log_emg = (
        0.5 * math.log(2 * math.pi)
        + jnp.log(ls)
        + 0.5 * ls * ls
        - lam * e
        + jax.scipy.special.log_ndtr(e * (1.0 / sigma) - ls)
    )
    return jnp.logaddexp(jnp.log1p(-w) + q, jnp.log(w) + log_emg)


def node_loglik(
    cells: Float[Array, "cells 2"],
    hyp_pos: Float[Array, "nodes hyp 2"],
    hyp_logw: Float[Array, "nodes hyp"],
    hyp_sigma: Float[Array, " nodes"],
    z_i: Float[Array, " nodes"],
    use_i: Bool[Array, " nodes"],
    p_out: Float[Array, ""],
    nlos: tuple[Float[Array, ""], Float[Array, ""]] | None = None,
) -> Float[Array, " cells"]:
    """Log likelihood eq. (11) of one node over the grid: the sum over neighbours j with `use_i[j]`.

    Dense form: every (neighbour, hypothesis) pair is evaluated (`vmap`) and unused ones are masked.

    Args:
        cells: (C, 2) [m]. hyp_pos, hyp_logw: (N, H, 2), (N, H) hypotheses of every node.
        hyp_sigma: (N,) range std to use with each neighbour [m]. z_i: (N,) ranges to the
            neighbours [m] (NaN missing). use_i: (N,) which neighbours contribute. p_out,
            nlos: see `pair_loglik`.

    Returns:
        (C,) log likelihood (0 where no neighbour contributes).
    """
    zs = jnp.where(use_i, z_i, 0.0)
    per = jax.vmap(pair_loglik, in_axes=(None, 0, 0, 0, 0, None, None))(
        cells, hyp_pos, hyp_logw, zs, hyp_sigma, p_out, nlos
    )
    return jnp.sum(jnp.where(use_i[:, None], per, 0.0), axis=0)


def node_loglik_sparse(
    cells: Float[Array, "cells 2"],
    hyp_pos: Float[Array, "nodes hyp 2"],
    hyp_logw: Float[Array, "nodes hyp"],
    hyp_sigma: Float[Array, " nodes"],
    z_i: Float[Array, " nodes"],
    use_i: Bool[Array, " nodes"],
    p_out: Float[Array, ""],
    nlos: tuple[Float[Array, ""], Float[Array, ""]] | None = None,
    remat: bool = False,
) -> Float[Array, " cells"]:
    """`node_loglik` with the same arguments and result, skipping the work of neighbours without a
    range
    (`lax.cond` in a loop over neighbours: cost ~ used pairs x hypotheses x cells). Must not be
    `vmap`ped (a batched `cond` evaluates both branches); map it over nodes with `lax.map`.

    `remat=True` (when differentiated: tuning) recomputes each pair's factor in the backward pass
    instead of storing its (hypotheses x cells) intermediates for every pair of every node and
    epoch; same values."""
    n = hyp_logw.shape[0]

    def neighbour(j, acc):
        def add(acc):
            return acc + pair_loglik(cells, hyp_pos[j], hyp_logw[j], z_i[j], hyp_sigma[j], p_out, nlos)

        return jax.lax.cond(use_i[j], jax.checkpoint(add) if remat else add, lambda a: a, acc)

    return jax.lax.fori_loop(0, n, neighbour, jnp.zeros(cells.shape[:1], cells.dtype))


def window_estimate(
    logp: Float[Array, " cells"], cells: Float[Array, "cells 2"], r_est: Float[Array, ""]
) -> Float[Array, " 2"]:
    """Position estimate eq. (13): posterior-weighted mean of the cells closer than `r_est` to the
    MLE cell.

    The MLE cell itself is always included (so `r_est` below one cell gives the MLE cell).
    """
    m = jnp.argmax(logp)
    d2 = jnp.sum(jnp.square(cells - cells[m]), axis=-1)
    inwin = (d2 < r_est * r_est) | (d2 == 0)
    w = jax.nn.softmax(jnp.where(inwin, logp, -jnp.inf))
    return w @ cells


def mean_cov(
    logp: Float[Array, " cells"], cells: Float[Array, "cells 2"]
) -> tuple[Float[Array, " 2"], Float[Array, "2 2"]]:
    """Mean [m] and covariance [m^2] of a (normalised) grid posterior over the whole grid."""
    w = jnp.exp(logp - jax.nn.logsumexp(logp))
    mu = w @ cells
    dc = cells - mu
    return mu, (dc * w[:, None]).T @ dc


def flat_index(ix: Int[Array, ...], iy: Int[Array, ...], grid: Grid) -> Int[Array, ...]:
    """Flat cell index of `(ix, iy)`."""
    return ix * grid.n_side + iy
