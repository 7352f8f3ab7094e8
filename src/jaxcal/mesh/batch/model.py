"""The batch model, traced: parameters as arrays (`_Numbers`), the robust losses rho (Huber, Cauchy, LOS / NLOS /
outlier mixture) with their square roots and IRLS weights, the fitted state (`_State`: positions, common and
per-node range offsets), range errors, residuals, cost and the sparse Jacobian rows of the pairs.

Losses: rho(e) >= 0 in units of "nats"; sqrt_rho gives a residual f with f^2 / 2 = rho.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxcal.mesh.batch.params import LOSSES, BatchParams, Observations


class _Numbers(eqx.Module):
    """The numeric and categorical parameters as arrays, so that new values (a new loss included)
    do not recompile: the loss is chosen by an index, the offset model by two 0/1 switches."""

    sigma_r: Array
    node_bias_sigma_m: Array
    nlos_weight: Array
    nlos_mean_m: Array
    outlier_weight: Array
    outlier_span_m: Array
    loss_id: Array
    use_c: Array
    use_b: Array

    @classmethod
    def of(cls, p: BatchParams) -> _Numbers:
        def number(name: str) -> Array:
            return jnp.asarray(float(getattr(p, name)), dtype=float)

        return cls(
            sigma_r=number("sigma_r"),
            node_bias_sigma_m=number("node_bias_sigma_m"),
            nlos_weight=number("nlos_weight"),
            nlos_mean_m=number("nlos_mean_m"),
            outlier_weight=number("outlier_weight"),
            outlier_span_m=number("outlier_span_m"),
            loss_id=jnp.asarray(LOSSES.index(p.loss)),
            use_c=jnp.asarray(float(p.bias != "none")),
            use_b=jnp.asarray(float(p.bias == "node")),
        )

    def with_loss(self, loss: str) -> _Numbers:
        return eqx.tree_at(lambda nb: nb.loss_id, self, jnp.asarray(LOSSES.index(loss)))


def _mixture_logpdf(e, nb: _Numbers):
    """log p(e) of the range error e = z - model [m]: LOS Gaussian, NLOS exponentially modified
    Gaussian (Gaussian convolved with a positive exponential of mean nlos_mean_m), uniform outliers."""
    s, lam = nb.sigma_r, 1.0 / nb.nlos_mean_m
    w_out, w_nlos = nb.outlier_weight, nb.nlos_weight
    w_los = 1.0 - w_nlos - w_out
    log_los = jnp.log(w_los) - 0.5 * (e / s) ** 2 - jnp.log(s * jnp.sqrt(2 * jnp.pi))
    log_nlos = (
        jnp.log(jnp.maximum(w_nlos, 1e-300))
        + jnp.log(lam)
        + 0.5 * (lam * s) ** 2
        - lam * e
        + jax.scipy.special.log_ndtr(e / s - lam * s)
    )
    log_out = jnp.broadcast_to(jnp.log(jnp.maximum(w_out, 1e-300)) - jnp.log(nb.outlier_span_m), e.shape)
    return jax.scipy.special.logsumexp(jnp.stack([log_los, log_nlos, log_out]), axis=0)


def _mixture_logpdf_bound(nb: _Numbers):
    """An upper bound of the mixture density's log (each component's density is bounded)."""
    s, lam = nb.sigma_r, 1.0 / nb.nlos_mean_m
    g = 1.0 / (s * jnp.sqrt(2 * jnp.pi))
    bound = (
        (1.0 - nb.nlos_weight - nb.outlier_weight) * g
        + nb.nlos_weight * jnp.minimum(lam, g)
        + nb.outlier_weight / nb.outlier_span_m
    )
    return jnp.log(bound) + 1e-3  # strictly above: sqrt(rho) stays smooth


def _select(loss_id, branches):
    """branches[loss_id], elementwise; every branch is finite (and has finite gradients) everywhere."""
    out = branches[0]
    for k, b in enumerate(branches[1:], start=1):
        out = jnp.where(loss_id == k, b, out)
    return out


def _rho(e, nb: _Numbers):
    """Robust cost of range errors e [m] (elementwise), for the loss `LOSSES[nb.loss_id]`."""
    u = e / nb.sigma_r
    a = jnp.abs(u)
    l2 = 0.5 * u * u
    huber = jnp.where(a <= 1.0, l2, a - 0.5)
    cauchy = 0.5 * jnp.log1p(u * u)
    mixture = _mixture_logpdf_bound(nb) - _mixture_logpdf(e, nb)
    return _select(nb.loss_id, (l2, huber, cauchy, mixture))


def _sqrt_rho(e, nb: _Numbers):
    """Residual f with f^2 / 2 = rho(e), smooth (and with finite derivatives) at e = 0."""
    u = e / nb.sigma_r
    a = jnp.abs(u)
    huber = jnp.where(a <= 1.0, u, jnp.sign(u) * jnp.sqrt(jnp.maximum(2.0 * a - 1.0, 1.0)))
    t = u * u  # cauchy: u * sqrt(log1p(t) / t), with the ratio's series near 0
    small = t < 1e-8
    ts = jnp.where(small, 1.0, t)
    cauchy = u * jnp.sqrt(jnp.where(small, 1.0 - 0.5 * t, jnp.log1p(ts) / ts))
    mixture = jnp.sqrt(2.0 * (_mixture_logpdf_bound(nb) - _mixture_logpdf(e, nb)))
    return _select(nb.loss_id, (u, huber, cauchy, mixture))


def _rho_of(nb: _Numbers, e: Array) -> Array:
    return _rho(e, nb)


def _sqrt_rho_of(nb: _Numbers, e: Array) -> Array:
    return _sqrt_rho(e, nb)


def _irls_weight(e, nb: _Numbers):
    """IRLS weight psi(e) / e * sigma_r^2 (1 for l2), >= 0; psi = d rho / d e."""
    rho1 = lambda x: _rho(x, nb)  # noqa: E731
    d1 = jax.vmap(jax.grad(rho1))(e)
    d2 = jax.vmap(jax.grad(jax.grad(rho1)))(e)
    small = jnp.abs(e) < 1e-9
    w = jnp.where(small, d2, d1 / jnp.where(small, 1.0, e))
    return jnp.maximum(w, 0.0) * nb.sigma_r**2


class _State(eqx.Module):
    x: Float[Array, "n d"]
    c: Float[Array, ""]
    b: Float[Array, " n"]


def _errors(state: _State, obs: Observations, nb: _Numbers):
    """Range errors e = z - model [m] of every observation."""
    diff = state.x[obs.i] - state.x[obs.j]
    sq = jnp.sum(diff * diff, axis=-1)
    dist = jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)
    model = dist + nb.use_c * state.c + nb.use_b * (state.b[obs.i] + state.b[obs.j])
    return obs.z - model


def _prior_scales(nb: _Numbers):
    """Prior widths [m] of c and b: unused offsets are pinned at zero (keeps full column rank)."""
    sc = jnp.where(nb.use_c > 0, 10.0, 1e-3)
    sb = jnp.where(nb.use_b > 0, nb.node_bias_sigma_m, 1e-3)
    return sc, sb


def _residuals(state: _State, args):
    obs, nb = args
    f = _sqrt_rho(_errors(state, obs, nb), nb) * jnp.sqrt(obs.w)
    sc, sb = _prior_scales(nb)
    return f, state.c / sc, state.b / sb


def _cost(state: _State, args) -> Array:
    f, pc, pb = _residuals(state, args)
    return 0.5 * (jnp.sum(f * f) + pc * pc + jnp.sum(pb * pb))


def _local_params(state: _State, obs: Observations):
    """Each observation's own parameters u (M, 2D + 3) = (x_i, x_j, c, b_i, b_j) and their indices
    (M, 2D + 3) into `ravel_pytree(state)` = (x.ravel(), c, b): the sparse rows of the Jacobian."""
    m, dim = state.x.shape
    u = jnp.concatenate(
        [
            state.x[obs.i],
            state.x[obs.j],
            jnp.broadcast_to(state.c, obs.i.shape)[:, None],
            state.b[obs.i][:, None],
            state.b[obs.j][:, None],
        ],
        axis=1,
    )
    ax = jnp.arange(dim)
    idx = jnp.concatenate(
        [
            obs.i[:, None] * dim + ax,
            obs.j[:, None] * dim + ax,
            jnp.full((obs.i.shape[0], 1), m * dim),
            m * dim + 1 + obs.i[:, None],
            m * dim + 1 + obs.j[:, None],
        ],
        axis=1,
    )
    return u, idx


def _rows(state: _State, args):
    """Every residual of `_residuals` with its local Jacobian and parameter indices (`SparseLevenbergMarquardt`).

    A pair's residual depends on (x_i, x_j, c, b_i, b_j) only; the prior rows on c and on one b_k. Indices
    are into `ravel_pytree(state)` = (x.ravel(), c, b).
    """
    obs, nb = args
    m, dim = state.x.shape
    sc, sb = _prior_scales(nb)

    def pair(u, z, w):
        xi, xj, c, bi, bj = u[:dim], u[dim : 2 * dim], u[2 * dim], u[2 * dim + 1], u[2 * dim + 2]
        one = Observations(jnp.zeros(1, int), jnp.ones(1, int), z[None], w[None])
        st = _State(jnp.stack([xi, xj]), c, jnp.stack([bi, bj]))
        return (_sqrt_rho(_errors(st, one, nb), nb) * jnp.sqrt(one.w))[0]

    u, idx = _local_params(state, obs)
    f = jax.vmap(pair)(u, obs.z, obs.w)
    g = jax.vmap(jax.jacfwd(pair))(u, obs.z, obs.w)
    n_loc = 2 * dim + 3
    # prior rows: c / sc on the c column, b_k / sb on b_k's column (the other local entries are zero)
    g_c = jnp.zeros((1, n_loc)).at[0, 2 * dim].set(1.0 / sc)
    i_c = jnp.full((1, n_loc), m * dim)
    g_b = jnp.zeros((m, n_loc)).at[:, 0].set(1.0 / sb)
    i_b = jnp.broadcast_to((m * dim + 1 + jnp.arange(m))[:, None], (m, n_loc))
    return (
        jnp.concatenate([f, jnp.reshape(state.c / sc, (1,)), state.b / sb]),
        jnp.concatenate([g, g_c, g_b]),
        jnp.concatenate([idx, i_c, i_b]),
    )


def _error_rows(state: _State, obs: Observations, nb: _Numbers):
    """Range errors e (M,) with their local Jacobians (M, 2D + 3) with respect to (x_i, x_j, c, b_i, b_j)
    and those parameters' indices into `ravel_pytree(state)` = (x.ravel(), c, b)."""
    dim = state.x.shape[1]

    def one(u, z):
        st = _State(jnp.stack([u[:dim], u[dim : 2 * dim]]), u[2 * dim], u[2 * dim + 1 :])
        return _errors(st, Observations(jnp.zeros(1, int), jnp.ones(1, int), z[None], jnp.ones(1)), nb)[0]

    u, idx = _local_params(state, obs)
    return jax.vmap(one)(u, obs.z), jax.vmap(jax.grad(one))(u, obs.z), idx
