"""Covariances of the batch fit: the Laplace covariance of the all-ranges fit, the pair errors and Jacobian
that the pair-level covariance (`jaxcal.mesh.pair_covariance`) takes, how covariances are combined
(`covariance_union`, `posterior_excess`), and which nodes they rest on (`_covariance_nodes`: those the
measurement graph fixes in the frame)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from jaxcal.mesh import identify
from jaxcal.mesh.batch.model import _error_rows, _errors, _irls_weight, _Numbers, _prior_scales, _State
from jaxcal.mesh.batch.params import Observations
from jaxcal.mesh.pair_covariance import pair_covariance, pair_spread
from jaxcal.mesh.sparse_lm import normal_equations


@eqx.filter_jit
def _covariance(free: Array, template: Array, mask: Array, c: Array, b: Array, obs: Observations, nb: _Numbers):
    """Covariance of the free position coordinates (plus offsets) in the anchor frame.

    J^T W J is accumulated from each range's few nonzero derivatives (`sparse_lm.normal_equations`), so
    memory follows the number of parameters squared, not ranges times parameters.

    Returns (cov of free coordinates (F, F), residual sigma^2 [m^2]).
    """
    m, dim = template.shape
    idx = jnp.nonzero(mask.ravel(), size=free.shape[0])[0]
    x = template.ravel().at[idx].set(free).reshape(template.shape)
    e, g, gi = _error_rows(_State(x, c, b), obs, nb)
    n_b = b.shape[0]
    w = _irls_weight(e, nb) * obs.w
    n_par = free.shape[0] + nb.use_c + nb.use_b * n_b
    dof = jnp.maximum(jnp.sum(obs.w) - n_par, 1.0)
    s2 = jnp.sum(w * e * e) / dof
    h_all, _ = normal_equations(e, g * jnp.sqrt(w / s2)[:, None], gi, m * dim + 1 + n_b, chunk=1 << 16)
    sel = jnp.concatenate([idx, m * dim + jnp.arange(1 + n_b)])  # (free coordinates, c, b)
    h = h_all[sel][:, sel]
    # Unused offsets are pinned by a stiff prior; per-node offsets get their Gaussian prior.
    sc, sb = _prior_scales(nb)
    prior = jnp.concatenate([jnp.zeros(free.shape[0]), jnp.stack([1.0 / sc**2]), jnp.full(n_b, 1.0 / sb**2)])
    h = h + jnp.diag(prior)
    cov = jnp.linalg.inv(h)
    f = free.shape[0]
    return cov[:f, :f], s2


def covariance_union(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The covariance a + (b - a)_+ ((.)_+ the positive semi-definite part): at least as large as a and as
    b in every direction (a + (b - a)_+ = b + (b - a)_-), symmetric PSD when a and b are. Coordinates
    where b - a is not finite (a node the pairs do not fix) get NaN rows and columns."""
    a = 0.5 * (a + a.T)
    d = 0.5 * (b + b.T) - a
    # coordinates the ranges do not fix (a singular sandwich: inf / NaN) are undefined: NaN rows and columns
    ok = np.isfinite(d).all(axis=0) & np.isfinite(d).all(axis=1) & (np.abs(d).max(axis=0, initial=0) < 1e150)
    out = np.full_like(a, np.nan)
    if ok.any():
        sub = np.ix_(ok, ok)
        try:
            lam, vec = np.linalg.eigh(d[sub])
        except np.linalg.LinAlgError:
            return out
        out[sub] = a[sub] + (vec * np.maximum(lam, 0.0)) @ vec.T
    return 0.5 * (out + out.T)


def posterior_excess(posterior: np.ndarray, laplace: np.ndarray, nu: float) -> np.ndarray:
    """What the posterior of `estimate=mean` adds to its own linearisation: (k C - L)_+, with C (`posterior`)
    the posterior sample covariance, L (`laplace`) the Laplace covariance of the same model with a Gaussian
    likelihood of the same scale s, (J^T W J / s^2 + prior)^-1, and k (`fisher_ratio`) the Student-t
    likelihood's information relative to that Gaussian ((.)_+ the positive semi-definite part).
    Where the ranges fix the nodes to first order k C ~ L and this is ~0 (Monte Carlo noise); where the
    posterior is curved or skewed (a weakly determined direction) it is the width the linearised pair covariance
    (`pair_covariance`) cannot see. The posterior itself is not a covariance of the error: it has no per-pair
    systematic errors that the geometry absorbs, and its Cauchy tails make it twice as wide as its scale in
    every well-determined direction; the union of the two (before) was too wide in the family benchmarks
    (NEES/dof median 0.48-0.56, coverage 98-100 %)."""
    lap = 0.5 * (laplace + laplace.T)
    return covariance_union(lap, fisher_ratio(posterior, lap, nu) * posterior) - lap


def fisher_ratio(posterior: np.ndarray, laplace: np.ndarray, nu: float) -> float:
    """k of `posterior_excess`: the smaller of the Student-t's asymptotic Fisher information ratio
    (nu + 1) / (nu + 3) and 1 / the median generalised eigenvalue of C (`posterior`) over L (`laplace`).

    (nu + 1) / (nu + 3) holds with many redundant pairs per parameter. A sparse network (few redundant
    pairs: a frame pair or a weak node's pairs never measured) widens the heavy-tailed posterior over its
    linearisation in *every* direction (on the `weak` family the smallest ratio was 1.8-3.1, the median
    2.4-6.0, for 2 asymptotically): a width of the likelihood's tails, not of the estimate's error, which
    the pair covariance sizes. The median direction is taken as not curved, so only the directions wider
    than it count as excess. Falls back to the asymptotic ratio where L is not positive definite."""
    k = (nu + 1.0) / (nu + 3.0)
    try:
        root = np.linalg.cholesky(0.5 * (laplace + laplace.T))
        white = np.linalg.solve(root, np.linalg.solve(root, 0.5 * (posterior + posterior.T)).T)
        g = np.linalg.eigvalsh(0.5 * (white + white.T))
    except np.linalg.LinAlgError:
        return k
    med = float(np.median(g)) if g.size else 0.0
    return min(k, 1.0 / med) if np.isfinite(med) and med > 0 else k


@eqx.filter_jit
def _pair_jacobian(theta: Array, template: Array, mask: Array, obs: Observations, nb: _Numbers):
    """Pair errors e = z - model (M,) at theta = (free coordinates, c, b) and their Jacobian (M, P)
    (`pair_covariance.pair_covariance` takes it; padding rows are zero)."""
    n_f = theta.shape[0] - 1 - template.shape[0]  # theta = (free (n_f,), c, b (m,))
    idx = jnp.nonzero(mask.ravel(), size=n_f)[0]

    def errs(th):
        x = template.ravel().at[idx].set(th[:n_f]).reshape(template.shape)
        return _errors(_State(x, th[n_f], th[n_f + 1 :]), obs, nb)

    real = obs.w > 0
    return jnp.where(real, errs(theta), 0.0), jax.jacfwd(errs)(theta) * real[:, None]


@eqx.filter_jit
def _range_weights(state: _State, obs: Observations, nb: _Numbers) -> Array:
    """IRLS weight of every observation at `state` (0 for padding), for the pair covariance: at most 1, the
    weight of a range under the Gaussian core. (The mixture's psi does not vanish at e = 0, its mode is
    shifted by the NLOS component, so psi(e) / e is singular near e = 0: one pair whose errors sat there
    weighed 10^4 times the others and sized every variance component alone, 10^5 m^2 for 0.3 m errors.)"""
    return jnp.minimum(_irls_weight(_errors(state, obs, nb), nb), 1.0) * obs.w


def _pair_level_covariance(
    ranges: np.ndarray,
    sub: np.ndarray,
    pair_i: np.ndarray,
    pair_j: np.ndarray,
    frame: np.ndarray,
    mask: np.ndarray,
    offset: float,
    node_offsets: np.ndarray,
    pairs: Observations,
    obs: Observations,
    nb: _Numbers,
) -> np.ndarray:
    """The covariance (P, P) of (free coordinates, c, b) under per-pair systematic errors sized from the data
    (`pair_covariance`), at the estimate reported: the pair medians (they do not depend on the fit), each pair
    weighted as the fit weighs its ranges.

    Args:
        ranges: (K, N, N) the range stream; sub: (m,) the active nodes among its N.
        pair_i, pair_j: (M,) indices (i < j, among the active nodes) of the measured pairs, the real rows of `pairs`.
        frame: (m, D) the estimate in the anchor frame; mask: (m, D) its free coordinates.
        offset, node_offsets: the estimate's common (scalar) and per-node ((m,)) range offsets [m].
        pairs: the per-pair median observations; obs: the observations the fit weighs (all ranges or `pairs`).
        nb: the numbers of the fit.
    """
    m = frame.shape[0]
    at = _State(jnp.asarray(frame), jnp.asarray(offset), jnp.asarray(node_offsets))
    theta = jnp.concatenate([jnp.asarray(frame[mask]), jnp.reshape(at.c, (1,)), at.b])
    e_pair, jac_pair = (np.asarray(a) for a in _pair_jacobian(theta, jnp.asarray(frame), jnp.asarray(mask), pairs, nb))
    w_obs = np.asarray(_range_weights(at, obs, nb))
    oi, oj = np.asarray(obs.i), np.asarray(obs.j)
    w_key = np.bincount(np.minimum(oi, oj) * m + np.maximum(oi, oj), weights=w_obs, minlength=m * m)
    w_pair = w_key[pair_i * m + pair_j]  # pairs: i < j, real rows first
    n_real = pair_i.size
    sc, sb = _prior_scales(nb)
    prior = np.concatenate([np.zeros(int(mask.sum())), [1.0 / float(sc) ** 2], np.full(m, 1.0 / float(sb) ** 2)])
    ok = w_pair > 0
    cov_pair, _ = pair_covariance(
        jac_pair[:n_real][ok],
        e_pair[:n_real][ok],
        w_pair[ok],
        pair_spread(ranges, sub[pair_i[ok]], sub[pair_j[ok]]),
        pair_i[ok],
        pair_j[ok],
        m,
        prior,
    )
    return cov_pair


def _covariance_nodes(
    pair_i: np.ndarray, pair_j: np.ndarray, m: int, anchors: tuple[int, int, int], dim: int, ids: tuple[str, ...]
) -> np.ndarray:
    """Which active nodes the covariance rests on, from the measurement graph (`identify`), not the ranges.

    Args: pair_i, pair_j: (M,) the measured pairs among the m active nodes; anchors: (a0, a1, a2) among them;
    dim: 2 or 3; ids: (m,) node ids.

    Returns `keep` (m,): the nodes the pairs fix in the frame. Only they and the pairs between them enter the
    covariance problem (an unfixed node's flex makes the Hessian singular and its NaN spread to every block).
    A frame with a mirror image (a frame node with only `dim` fixed neighbours) leaves only the frame's
    measured triangle fixed (`identify`), so nothing placed through the frame gets a covariance.
    """
    adj = np.zeros((m, m), dtype=bool)
    adj[pair_i, pair_j] = adj[pair_j, pair_i] = True
    return identify.identify(adj, anchors, dim, ids).fixed


def _restrict(obs: Observations, keep: np.ndarray) -> Observations:
    """`obs` with weight 0 for every observation touching a node not in `keep` (same shapes: no recompilation)."""
    k = jnp.asarray(keep)
    return eqx.tree_at(lambda o: o.w, obs, jnp.where(k[obs.i] & k[obs.j], obs.w, 0.0))
