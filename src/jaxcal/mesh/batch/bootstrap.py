"""`bias=auto`: whether fitting the common range offset is predicted to place the nodes better than leaving it
out, from a residual bootstrap of the network fit (`offset_bootstrap`)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array

from jaxcal import solver as S
from jaxcal.mesh.batch.fit import _solver
from jaxcal.mesh.batch.model import _errors, _Numbers, _residuals, _State
from jaxcal.mesh.batch.params import Observations


def _procrustes_rmse(x: Array, ref: Array) -> Array:
    """RMSE [m] of `x` after the best rigid motion (rotation and translation, no reflection) onto `ref`."""
    xc, rc = x - jnp.mean(x, axis=0), ref - jnp.mean(ref, axis=0)
    u, _, vt = jnp.linalg.svd(xc.T @ rc)
    d = jnp.sign(jnp.linalg.det(u @ vt))
    r = (u * jnp.concatenate([jnp.ones(x.shape[1] - 1), d[None]])) @ vt  # x @ r ~ ref
    return jnp.sqrt(jnp.mean(jnp.sum((xc @ r - rc) ** 2, axis=1)))


@eqx.filter_jit
def offset_bootstrap(
    state: _State,
    observations: Observations,
    numbers: _Numbers,
    key: Array,
    n_boot: int,
    solver: str,
    tol: float,
    max_steps: int,
    tail: int = 0,
) -> tuple[Array, Array]:
    """Predicted position error of fitting the common range offset c or leaving it out (`bias=auto`).

    A common offset is not always worth estimating: where the geometry is weak (e.g. nearly planar 3-D
    scenes) c trades off against the poorly determined directions, and the variance its estimate adds
    can exceed the bias of ignoring it. Which one wins is estimated by a residual bootstrap of the
    network fit: replicate observations are the fitted model plus residuals resampled with replacement
    (inflated for the degrees of freedom the fit used up); each replicate is refitted locally (from the
    fit) with and without c, and the rigidly aligned position RMSE against the fitted positions is averaged.

    Args:
        state: the network-offset fit (positions (m, D), c, b).
        observations: the observations it was fitted to (padding has weight 0 and is never resampled).
        numbers: the numbers of that fit (`use_c` = 1).
        key: PRNG key; n_boot: replicates (static).

    Returns:
        ((2,) RMSE [m] of (with offset, without offset), averaged over the replicates; (n_boot, 2) outcome
        codes of the replicate fits (`jaxcal.solver.outcome`)).
    """
    e = _errors(state, observations, numbers)
    model = observations.z - e
    real = observations.w > 0
    logits = jnp.where(real, 0.0, -jnp.inf)
    # Fitted residuals are smaller than the errors by about sqrt((M - P) / M) (P fitted parameters):
    # resample them inflated by the inverse (the usual correction of a regression residual bootstrap).
    m, dim = state.x.shape
    n_par = dim * m - dim * (dim + 1) // 2 + 1 + numbers.use_b * m
    n_obs = jnp.sum(real)
    e_boot = e * jnp.sqrt(n_obs / jnp.maximum(n_obs - n_par, 1.0))
    numbers_none = eqx.tree_at(lambda t: t.use_c, numbers, jnp.zeros_like(numbers.use_c))
    start_none = eqx.tree_at(lambda t: t.c, state, jnp.zeros_like(state.c))

    def one(k):
        pick = jax.random.categorical(k, logits, shape=e.shape)
        zb = jnp.where(real, model + e_boot[pick], observations.z)
        obs_b = Observations(observations.i, observations.j, zb, observations.w)

        def fit(y0, nbk):
            sol = optx.least_squares(
                _residuals, _solver(solver, tol, tail), y0, (obs_b, nbk), max_steps=max_steps, throw=False
            )
            return _procrustes_rmse(sol.value.x, state.x) ** 2, S.outcome(sol)

        return jax.tree.map(lambda *a: jnp.stack(a), fit(state, numbers), fit(start_none, numbers_none))

    sq, codes = jax.vmap(one)(jax.random.split(key, n_boot))
    return jnp.sqrt(jnp.mean(sq, axis=0)), codes
