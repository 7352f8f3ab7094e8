"""The robust fit: start configurations (classical MDS, SMACOF, random SMACOF starts, user starts), their
refinement by least squares with a graduated loss scale, the relocation round's candidate moves, and the
all-ranges refinement by iteratively reweighted least squares."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array

from jaxcal import solver as S
from jaxcal.mesh import mds
from jaxcal.mesh.batch.model import (
    _cost,
    _errors,
    _irls_weight,
    _Numbers,
    _residuals,
    _rho_of,
    _rows,
    _sqrt_rho_of,
    _State,
)
from jaxcal.mesh.batch.params import Observations
from jaxcal.mesh.relocation import relocation_moves
from jaxcal.mesh.sparse_lm import SparseLevenbergMarquardt


def _solver(name: str, tol: float, tail: int = 0):
    """The least-squares solver `name`; `tail`: the per-node offsets (last in the state) enter no residual
    (`bias` other than `node`), which `lm` exploits (`SparseLevenbergMarquardt.diag_tail`)."""
    if name == "gn":
        return optx.GaussNewton(rtol=tol, atol=tol)
    if name == "lm_dense":
        return optx.LevenbergMarquardt(rtol=tol, atol=tol)
    return SparseLevenbergMarquardt(rtol=tol, atol=tol, rows=_rows, diag_tail=tail)


@eqx.filter_jit
def _initial_starts(
    d_pair: Array, w_pair: Array, key: Array, dim: int, init: str, n_starts: int, smacof_iters: int
) -> Array:
    """(S, n, dim) start configurations from classical MDS, SMACOF and random SMACOF starts."""
    n = d_pair.shape[0]
    full = mds.complete_distances(jnp.where(w_pair > 0, d_pair, jnp.nan))
    x_cmds = mds.classical_mds(full, dim)
    # A tiny deterministic jitter breaks the exact degeneracy of a planar MDS in 3-D.
    jitter = 1e-3 * jax.random.normal(jax.random.fold_in(key, 1), x_cmds.shape)
    x_cmds = x_cmds + jitter
    if init == "cmds":
        return x_cmds[None]
    x_sm = mds.smacof(d_pair, w_pair, x_cmds, smacof_iters)
    if init == "smacof":
        return x_sm[None]
    span = jnp.max(jnp.where(jnp.isfinite(full), full, 0.0))
    rand = jax.random.uniform(key, (n_starts, n, dim), minval=-0.5, maxval=0.5) * span
    rand_sm = jax.vmap(lambda x0: mds.smacof(d_pair, w_pair, x0, smacof_iters))(rand)
    return jnp.concatenate([x_cmds[None], x_sm[None], rand_sm], axis=0)


def _extra_starts(starts: np.ndarray, sub: np.ndarray, base: np.ndarray, dim: int) -> np.ndarray:
    """(E, N, D) user starts -> (2E, m, dim) on the connected nodes: NaN rows from `base`, plus mirror images."""
    ex = np.asarray(starts, dtype=np.float64)
    if ex.ndim == 2:
        ex = ex[None]
    ex = ex[:, sub, :dim]
    if ex.shape[-1] < dim:  # 2-D modes for a 3-D fit: z from the MDS start
        ex = np.concatenate(
            [ex, np.broadcast_to(base[None, :, ex.shape[-1] :], ex.shape[:2] + (dim - ex.shape[-1],))], axis=-1
        )
    ex = np.where(np.isfinite(ex), ex, base[None])
    mirror = ex.copy()
    mirror[..., 1] *= -1.0
    return np.concatenate([ex, mirror])


@eqx.filter_jit
def _fit_starts(
    y0s: _State,
    obs: Observations,
    nb: _Numbers,
    solver: str,
    tol: float,
    max_steps: int,
    factors: Array | None = None,
    coarse_tol: float | None = None,
    tail: int = 0,
):
    """Refine every start (a batched `_State`; vmapped least squares); returns final states, costs and
    the outcome codes of their last fits (`jaxcal.solver.outcome`).

    With `factors` (G,) the loss scale is graduated (graduated non-convexity): the fit is solved
    with sigma_r * factors[0], ..., sigma_r * factors[-1] in turn, each warm-started from the last. A wide
    scale first pulls every start towards the bulk of the data before a narrow, redescending loss
    decides which ranges are outliers, so gross errors in the start do not trap the fit. With `coarse_tol`
    (`solver="lm"` only), every stage but the last stops at that tolerance (or `tol`, if looser). `tail`:
    see `_solver` (static; the number of nodes when the model has no per-node offsets, else 0).
    """
    args = (obs, nb)
    factors = jnp.ones(1) if factors is None else factors
    last = jnp.arange(factors.shape[0]) == factors.shape[0] - 1
    coarse = solver == "lm" and coarse_tol is not None

    def one(y0):
        def stage(y, fl):
            factor, is_last = fl
            nbk = eqx.tree_at(lambda t: t.sigma_r, nb, nb.sigma_r * factor)
            if coarse:
                tol_k = jnp.where(is_last, tol, max(tol, coarse_tol))
                opt = SparseLevenbergMarquardt(rtol=tol_k, atol=tol_k, rows=_rows, diag_tail=tail)
            else:
                opt = _solver(solver, tol, tail)
            sol = optx.least_squares(_residuals, opt, y, (obs, nbk), max_steps=max_steps, throw=False)
            return sol.value, S.outcome(sol)

        y, codes = jax.lax.scan(stage, y0, (factors, last))
        return y, _cost(y, args), codes[-1]

    # one start at a time: each stops at its own step count (a vmapped while loop runs every start as
    # long as the slowest, and a batched scatter of the sparse normal equations is slow on CPU)
    return jax.lax.map(one, y0s)


def _relocation_candidates(state: _State, table, nb: _Numbers, grid_n: int, n_cand: int) -> _State:
    """Batched starts of one relocation round: `state` with one node moved to another basin, for the
    `n_cand` nodes whose locally refined move lowers the total cost most (every node when m <= n_cand)."""
    m = state.x.shape[0]
    nbr, d_nbr, w_nbr = (jnp.asarray(a) for a in table)
    # Score grid points with a loss no narrower than the grid spacing, or the true basin can be missed
    # between two grid points; the refinement after the move uses the real scale.
    lo, hi = jnp.min(state.x, axis=0), jnp.max(state.x, axis=0)
    spacing = 1.5 * jnp.max(hi - lo) / (grid_n - 1)  # grid span: the scene plus a quarter on either side
    nb_grid = eqx.tree_at(lambda t: t.sigma_r, nb, jnp.maximum(nb.sigma_r, spacing))
    offset = nb.use_c * state.c + nb.use_b * (state.b[:, None] + state.b[nbr])
    moved, delta = relocation_moves(
        state.x,
        offset,
        nbr,
        d_nbr,
        w_nbr,
        jax.tree_util.Partial(_rho_of, nb_grid),
        jax.tree_util.Partial(_sqrt_rho_of, nb),
        grid_n,
        3.0 * nb_grid.sigma_r,
    )
    delta = np.where(np.isfinite(np.asarray(delta)), np.asarray(delta), np.inf)
    pick = np.arange(m) if m <= n_cand else np.argsort(delta, kind="stable")[:n_cand]
    xs = jnp.repeat(state.x[None], pick.size, axis=0).at[np.arange(pick.size), pick].set(moved[pick])
    return _State(xs, jnp.broadcast_to(state.c, (pick.size,)), jnp.broadcast_to(state.b, (pick.size, m)))


@eqx.filter_jit
def _irls_all(
    y0: _State,
    obs: Observations,
    pair_i: Array,
    pair_j: Array,
    pair_of_obs: Array,
    nb: _Numbers,
    solver: str,
    tol: float,
    max_steps: int,
    n_iter: int,
    tail: int = 0,
) -> tuple[_State, Array]:
    """Minimise the robust cost over every single range by iteratively reweighted least squares.

    With fixed weights w_k the cost of a pair's ranges, sum_k w_k (z_k - m)^2, equals
    W (zbar - m)^2 + const with W = sum_k w_k and zbar the weighted mean, so each inner
    least-squares problem has one residual per pair whatever the number of epochs. Returns the state
    and the outcome code of the last round's fit (`jaxcal.solver.outcome`).
    """
    n_pairs = pair_i.shape[0]

    def step(state, _):
        e = _errors(state, obs, nb)
        w = _irls_weight(e, nb) * obs.w
        wsum = jax.ops.segment_sum(w, pair_of_obs, n_pairs)
        zbar = jax.ops.segment_sum(w * obs.z, pair_of_obs, n_pairs) / jnp.maximum(wsum, 1e-300)
        pairs = Observations(pair_i, pair_j, zbar, wsum)
        sol = optx.least_squares(
            _residuals,
            _solver(solver, tol, tail),
            state,
            (pairs, nb.with_loss("l2")),
            max_steps=max_steps,
            throw=False,
        )
        return sol.value, S.outcome(sol)

    state, codes = jax.lax.scan(step, y0, None, length=n_iter)
    return state, codes[-1]


@eqx.filter_jit
def _pair_locations(
    state: _State, obs: Observations, pair_i: Array, pair_j: Array, pair_of_obs: Array, nb: _Numbers
) -> Observations:
    """One observation per pair: the IRLS-weighted mean of its ranges at `state` (the pair's robust
    location that the all-epochs fit uses), weight 1 (0 for padding)."""
    n_pairs = pair_i.shape[0]
    w = _irls_weight(_errors(state, obs, nb), nb) * obs.w
    wsum = jax.ops.segment_sum(w, pair_of_obs, n_pairs)
    zbar = jax.ops.segment_sum(w * obs.z, pair_of_obs, n_pairs) / jnp.maximum(wsum, 1e-300)
    return Observations(pair_i, pair_j, zbar, (wsum > 0).astype(zbar.dtype))
