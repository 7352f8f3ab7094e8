"""Single-node relocation of a mesh fit, local to each node's neighbours (`batch`, `relocate_rounds`).

A multi-start fit can leave a weakly constrained node in the wrong basin: flipped through the line of its
neighbours, or pulled by a gross outlier. Relocation tries, for every node, the best point of a grid over
the scene (its own robust cost, every other node fixed) outside its current basin. The exhaustive form
refits the whole network from every such move (N full fits per round). Here each move is first refined
locally (the node alone, its neighbours fixed; a few Levenberg-Marquardt steps on its own residuals,
vmapped over the nodes), which gives the exact change of the total cost of the moved network, and only
the few moves that lower it most are refitted globally: O(N) small fits and a constant number of full
ones per round.

Everything here works on padded neighbour tables (N, K), K the largest degree, so its cost and memory grow
with the measured pairs, not with N^2.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

__all__ = ["neighbour_table", "relocation_moves"]


K_STEP = 8  # the width of `neighbour_table` is a multiple of this (shared compilations)


def neighbour_table(d_pair: np.ndarray, w_pair: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Padded neighbour lists of a symmetric pair matrix.

    Args:
        d_pair: (N, N) measured distances [m] (any value where unmeasured); w_pair: (N, N) weights, 0 =
            not measured.

    Returns:
        (nbr, d, w): (N, K) neighbour indices, their distances and weights; padding has index 0 and weight 0.
        K is the most neighbours of a node rounded up to a multiple of `K_STEP` (at most N - 1): K is a
        shape of `relocation_moves`, and networks of N nodes whose largest degree differs by a few share
        one compilation (it was compiled anew for most of 20 random networks of 16 nodes).
    """
    n = d_pair.shape[0]
    has = (np.asarray(w_pair) > 0) & ~np.eye(n, dtype=bool)
    most = int(has.sum(axis=1).max(initial=0))
    k = max(min(-(-most // K_STEP) * K_STEP, n - 1), most, 1)
    nbr, d, w = np.zeros((n, k), dtype=np.int64), np.zeros((n, k)), np.zeros((n, k))
    for a in range(n):
        js = np.flatnonzero(has[a])
        nbr[a, : js.size], d[a, : js.size], w[a, : js.size] = js, np.nan_to_num(d_pair[a, js]), w_pair[a, js]
    return nbr, d, w


def _dist(p: Array, q: Array) -> Array:
    """Distances between p (..., D) and q (..., D), with a finite gradient at zero."""
    sq = jnp.sum((p - q) ** 2, axis=-1)
    return jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)


@eqx.filter_jit
def relocation_moves(
    x: Float[Array, "n d"],
    offset: Float[Array, "n k"],
    nbr: Int[Array, "n k"],
    d_nbr: Float[Array, "n k"],
    w_nbr: Float[Array, "n k"],
    rho_grid: Callable,
    sqrt_rho: Callable,
    grid_n: int,
    exclude_m: Array,
    n_steps: int = 30,
):
    """Every node's best move to another basin and what it changes in the total robust cost.

    Args:
        x: (N, D) current positions [m]. offset: (N, K) range offsets of each pair in the model (common and
            per-node) [m]. nbr, d_nbr, w_nbr: `neighbour_table`.
        rho_grid: e -> robust cost of range errors [m] used to score grid points (a loss no narrower than
            the grid spacing); sqrt_rho: e -> residual whose square / 2 is the fit's robust cost.
            Both are `jax.tree_util.Partial`s (elementwise).
        grid_n: grid points per axis (static); exclude_m: grid points nearer than this to the node's
            current position are not a move (the current basin is already a local optimum).
        n_steps: local Levenberg-Marquardt steps (static).

    Returns:
        (moved (N, D): the grid point of least cost outside the current basin, before refinement;
        delta (N,): change of the total cost when the node alone moves there and is refined locally).
    """
    m, dim = x.shape
    lo, hi = jnp.min(x, axis=0), jnp.max(x, axis=0)
    margin = 0.25 * jnp.max(hi - lo)
    axes = [jnp.linspace(lo[a] - margin, hi[a] + margin, grid_n) for a in range(dim)]
    g = jnp.stack(jnp.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, dim)  # (G, D)

    def best_point(k):
        dist = _dist(g[:, None, :], x[nbr[k]][None, :, :])  # (G, K)
        cost = jnp.sum(w_nbr[k][None, :] * rho_grid(d_nbr[k][None, :] - dist - offset[k][None, :]), axis=1)
        near = _dist(g, x[k]) < exclude_m
        return g[jnp.argmin(jnp.where(near, jnp.inf, cost))]

    moved = jax.lax.map(best_point, jnp.arange(m))  # sequential over nodes: (G, K) memory at a time

    def residuals(p, k):
        return sqrt_rho(d_nbr[k] - _dist(p[None, :], x[nbr[k]]) - offset[k]) * jnp.sqrt(w_nbr[k])

    def refine(p0, k):
        def step(carry, _):
            p, lam = carry
            r = residuals(p, k)
            jac = jax.jacfwd(residuals)(p, k)
            h = jac.T @ jac
            delta = -jnp.linalg.solve(h + lam * jnp.eye(dim) * (1.0 + jnp.trace(h) / dim), jac.T @ r)
            r_new = residuals(p + delta, k)
            better = jnp.sum(r_new * r_new) < jnp.sum(r * r)
            return (jnp.where(better, p + delta, p), jnp.where(better, lam / 3.0, lam * 4.0)), None

        (p, _), _ = jax.lax.scan(step, (p0, jnp.asarray(1e-3)), None, length=n_steps)
        return 0.5 * jnp.sum(residuals(p, k) ** 2)

    before = jax.vmap(lambda k: 0.5 * jnp.sum(residuals(x[k], k) ** 2))(jnp.arange(m))
    after = jax.vmap(refine)(moved, jnp.arange(m))
    return moved, after - before
