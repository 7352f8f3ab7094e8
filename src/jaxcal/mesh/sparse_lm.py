"""Levenberg-Marquardt for least squares whose residual rows each touch a few parameters (an Optimistix solver).

A mesh fit has one residual per measured pair, and each depends only on the two nodes' coordinates and
offsets and the common offset: 2 D + 3 of the P = N D + 1 + N parameters. A dense solver materialises the
(M, P) Jacobian (P forward passes) and factors it at O(M P^2) per step, which for networks of hundreds of
nodes is what the whole fit costs. Here the caller gives each row's local Jacobian (R, L) and the
parameter index of each of its L entries; the normal matrix J^T J = sum_r g_r g_r^T and the gradient
J^T f are accumulated from them in O(R L^2), and the damped system (J^T J + lambda I) delta = -J^T f is
solved by a Cholesky factorisation (O(P^3) with a tiny constant: P = 901 at N = 300 in 2-D).

The iteration is the classical one (Nielsen's damping update, Madsen, Nielsen & Tingleff 2004, eq. 2.21):
a step is accepted when it lowers the cost; lambda shrinks after a good step and grows after a rejected
one. Termination follows Optimistix's Cauchy criterion (`optx.LevenbergMarquardt`): an accepted step that
changes neither y nor the residuals by more than atol + rtol |.| (max norm).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

__all__ = ["SparseLevenbergMarquardt", "normal_equations"]

RowsFn = Callable[[Any, Any], tuple[Float[Array, " r"], Float[Array, "r l"], Int[Array, "r l"]]]


def normal_equations(
    f: Float[Array, " r"], g: Float[Array, "r l"], idx: Int[Array, "r l"], n_par: int, chunk: int | None = None
):
    """J^T J (P, P) and J^T f (P,) from rows: residuals f, local Jacobians g and their parameter indices.

    Entries with a zero local derivative may carry any valid index (they add nothing). With `chunk`, the
    rows are accumulated `chunk` at a time (memory O(chunk L^2) instead of O(R L^2) for R in the millions).
    """
    if chunk is None or f.shape[0] <= chunk:
        grad = jnp.zeros(n_par).at[idx].add(g * f[:, None])
        h = jnp.zeros((n_par, n_par)).at[idx[:, :, None], idx[:, None, :]].add(g[:, :, None] * g[:, None, :])
        return h, grad
    pad = -f.shape[0] % chunk
    f, g, idx = (jnp.concatenate([a, jnp.zeros((pad,) + a.shape[1:], a.dtype)]) for a in (f, g, idx))
    blocks = tuple(a.reshape((-1, chunk) + a.shape[1:]) for a in (f, g, idx))

    def add(acc, blk):
        h, grad = normal_equations(*blk, n_par)
        return (acc[0] + h, acc[1] + grad), None

    (h, grad), _ = jax.lax.scan(add, (jnp.zeros((n_par, n_par)), jnp.zeros(n_par)), blocks)
    return h, grad


class _State(eqx.Module):
    f: Float[Array, " r"]  # residuals at the accepted y
    lam: Float[Array, ""]
    nu: Float[Array, ""]
    terminate: Bool[Array, ""]


class SparseLevenbergMarquardt(optx.AbstractLeastSquaresSolver):
    """Levenberg-Marquardt with the normal equations assembled from sparse residual rows.

    Attributes:
        rtol, atol: Cauchy termination tolerances (as `optx.LevenbergMarquardt`).
        rows: `rows(y, args) -> (f (R,), g (R, L), idx (R, L))`: every residual (the same values, in any
            order, as the function passed to `optx.least_squares`), its derivative with respect to the L
            parameters it depends on, and their positions in `ravel_pytree(y)`.
        lambda_floor: smallest damping relative to the mean diagonal of J^T J (keeps the factorisation
            finite along the gauge directions of a mesh, where J^T J is singular).
        diag_tail: K > 0 when the last K parameters are decoupled from the others and from each other
            (their block of J^T J is diagonal and the off-diagonal blocks are zero, e.g. offsets that no
            residual uses, held by their prior rows alone): the damped system is then solved by a
            Cholesky factorisation of the first P - K rows and elementwise on the tail, the same step at
            O((P - K)^3) (P = 3 N + 1 -> 2 N + 1 in a mesh fit without per-node offsets: 3.4x fewer flops).
            The caller guarantees the structure.
    """

    rtol: float
    atol: float
    rows: RowsFn = eqx.field(static=True, kw_only=True)
    lambda_floor: float = 1e-12
    norm: Callable = eqx.field(static=True, default=optx.max_norm)  # the criterion's norm (max |.|)
    diag_tail: int = eqx.field(static=True, default=0)

    def _eval(self, y, args):
        f, g, idx = self.rows(y, args)
        return f, g, idx

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        f, _, _ = self._eval(y, args)
        return _State(f, jnp.asarray(1.0, f.dtype), jnp.asarray(2.0, f.dtype), jnp.array(False))

    def step(self, fn, y, args, options, state: _State, tags):
        flat, unravel = ravel_pytree(y)
        f, g, idx = self._eval(y, args)
        h, grad = normal_equations(f, g, idx, flat.shape[0])
        diag = jnp.diagonal(h)
        lam = jnp.maximum(state.lam, self.lambda_floor * jnp.mean(diag))
        a = h + lam * jnp.eye(flat.shape[0], dtype=h.dtype)
        head = flat.shape[0] - self.diag_tail
        chol = jnp.linalg.cholesky(a[:head, :head])
        delta = -jax.scipy.linalg.cho_solve((chol, True), grad[:head])
        if self.diag_tail:
            delta = jnp.concatenate([delta, -grad[head:] / jnp.diagonal(a)[head:]])
        y_new = unravel(flat + delta)
        f_new, _, _ = self._eval(y_new, args)
        cost, cost_new = 0.5 * jnp.sum(f * f), 0.5 * jnp.sum(f_new * f_new)
        predicted = 0.5 * jnp.dot(delta, lam * delta - grad)  # model decrease, > 0 for a nonzero step
        rho = (cost - cost_new) / jnp.where(predicted > 0, predicted, 1.0)
        ok = jnp.isfinite(cost_new) & jnp.all(jnp.isfinite(delta)) & (cost_new <= cost) & (predicted > 0)
        small_y = jnp.max(jnp.abs(delta) / (self.atol + self.rtol * jnp.abs(flat))) < 1
        small_f = jnp.max(jnp.abs(f_new - f) / (self.atol + self.rtol * jnp.abs(f))) < 1
        # no step can lower the cost (e.g. at an exact optimum the model decrease is 0): done
        stalled = ~ok & ((predicted <= 0) | (lam > 1e16 * jnp.maximum(jnp.mean(diag), 1.0)))
        lam_ok = lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
        new = _State(
            f=jnp.where(ok, f_new, f),
            lam=jnp.where(ok, lam_ok, lam * state.nu),
            nu=jnp.where(ok, 2.0, 2.0 * state.nu),
            terminate=(ok & small_y & small_f) | stalled,
        )
        y_out = jax.tree.map(lambda a_, b_: jnp.where(ok, a_, b_), y_new, y)
        return y_out, new, None

    def terminate(self, fn, y, args, options, state: _State, tags):
        return state.terminate, optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}
