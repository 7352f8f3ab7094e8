"""Global initialisation of a mesh: distance-matrix completion, classical MDS and weighted SMACOF.

These give a local least-squares fit (`jaxcal.mesh.batch`) a start near the global optimum. All
positions are in an arbitrary frame (rigid motion and mirror image are free); callers fix the gauge.

Pure JAX; every function is jit-friendly (static shapes, `lax.fori_loop` for iterations).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["complete_distances", "classical_mds", "smacof", "stress", "pairwise_distances"]


def pairwise_distances(x: Float[Array, "n d"]) -> Float[Array, "n n"]:
    """(N, N) Euclidean distances between rows of `x`, with a gradient-safe zero diagonal."""
    diff = x[:, None, :] - x[None, :, :]
    sq = jnp.sum(diff * diff, axis=-1)
    safe = jnp.where(sq > 0, sq, 1.0)
    return jnp.where(sq > 0, jnp.sqrt(safe), 0.0)


def complete_distances(d: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """Fill missing entries of a symmetric distance matrix with shortest-path lengths (Floyd-Warshall).

    Shortest paths over measured links overestimate a missing Euclidean distance (triangle
    inequality), which is good enough as an MDS input for initialisation.

    Args:
        d: (N, N) distances [m]; NaN = not measured. Need not be symmetric (the smaller of the two
            directions is used for each link).

    Returns:
        (N, N) symmetric matrix, zero diagonal; `inf` between nodes that are not connected.
    """
    n = d.shape[0]
    g = jnp.where(jnp.isnan(d), jnp.inf, d)
    g = jnp.minimum(g, g.T)
    g = jnp.where(jnp.eye(n, dtype=bool), 0.0, g)

    def relax(k, g):
        return jnp.minimum(g, g[:, k, None] + g[None, k, :])

    return jax.lax.fori_loop(0, n, relax, g)


def classical_mds(d: Float[Array, "n n"], dim: int) -> Float[Array, "n dim"]:
    """Classical (Torgerson) MDS: the `dim` leading eigenvectors of the double-centred squared distances.

    Exact (up to a rigid motion and mirror image) for noise-free Euclidean distances of points that
    span `dim` dimensions.

    Args:
        d: (N, N) complete, finite distances [m].
        dim: embedding dimension (2 or 3); static.

    Returns:
        (N, dim) positions [m], centred at the origin.
    """
    n = d.shape[0]
    j = jnp.eye(n) - 1.0 / n
    b = -0.5 * j @ (d * d) @ j
    w, v = jnp.linalg.eigh(0.5 * (b + b.T))  # ascending eigenvalues
    w, v = w[::-1][:dim], v[:, ::-1][:, :dim]
    return v * jnp.sqrt(jnp.maximum(w, 0.0))


def stress(x: Float[Array, "n d"], d: Float[Array, "n n"], w: Float[Array, "n n"]) -> Float[Array, ""]:
    """Weighted raw stress sum_{i<j} w_ij (||x_i - x_j|| - d_ij)^2 (entries with w = 0 are ignored)."""
    dx = pairwise_distances(x)
    r = jnp.where(w > 0, dx - jnp.where(w > 0, d, 0.0), 0.0)
    return 0.5 * jnp.sum(w * r * r)


def smacof(
    d: Float[Array, "n n"], w: Float[Array, "n n"], x0: Float[Array, "n d"], n_iter: int = 300
) -> Float[Array, "n d"]:
    """Weighted metric SMACOF (stress majorisation, de Leeuw 1977) from a start `x0`.

    Each Guttman transform `x <- V^+ B(x) x` does not increase the weighted stress, so the iteration
    is monotone; missing pairs simply get weight zero (no completion needed).

    Args:
        d: (N, N) target distances [m]; entries with zero weight may be NaN.
        w: (N, N) non-negative symmetric weights (0 = ignore the pair); the graph of w > 0 must be connected.
        x0: (N, D) start positions [m].
        n_iter: number of Guttman transforms; static.

    Returns:
        (N, D) positions [m] with (weakly) lower stress than `x0`.
    """
    n = x0.shape[0]
    w = 0.5 * (w + w.T) * (1.0 - jnp.eye(n))
    dd = jnp.where(w > 0, jnp.nan_to_num(d), 0.0)
    dd = 0.5 * (dd + dd.T)
    v = jnp.diag(jnp.sum(w, axis=1)) - w
    # V is singular along the all-ones vector; (V + 11^T/n)^-1 - 11^T/n is its pseudo-inverse.
    ones = jnp.ones((n, n)) / n
    v_pinv = jnp.linalg.inv(v + ones) - ones

    def step(_, x):
        dx = pairwise_distances(x)
        ratio = jnp.where(dx > 0, w * dd / jnp.where(dx > 0, dx, 1.0), 0.0)
        b = jnp.diag(jnp.sum(ratio, axis=1)) - ratio
        return v_pinv @ (b @ x)

    return jax.lax.fori_loop(0, n_iter, step, x0 - jnp.mean(x0, axis=0))
