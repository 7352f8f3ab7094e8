"""Optimistix outcomes checked in one place: every fit run with `throw=False` reads `sol.result` here.

A fit that stopped at `max_steps`, diverged or failed in its linear solves still returns a value; these
helpers turn its `sol.result` into a small integer code (`status`, any batch shape, inside jit), let a
caller retry a fit that ran out of steps with more of them (`retry_unconverged`), sum the codes up for the
`Result` params (`SolverReport.params`: `solver_status`, `solver_failed`) and say so in one warning line
(`SolverReport.warn`, logger `jaxcal`).

    sol = optx.least_squares(fn, solver, y0, args, max_steps=n, throw=False)
    value, code = sol.value, solver.outcome(sol)
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from typing import TypeVar

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, Int

__all__ = [
    "CONVERGED",
    "MAX_STEPS",
    "DIVERGED",
    "FAILED",
    "STATUS_NAMES",
    "STALL_STEPS",
    "status",
    "outcome",
    "SolverReport",
    "report",
    "retry_unconverged",
    "StartedBFGS",
    "newton_start",
]

CONVERGED, MAX_STEPS, DIVERGED, FAILED = 0, 1, 2, 3
# index = code; a larger code is a worse outcome, so the worst of several fits is their maximum
STATUS_NAMES = ("converged", "max_steps", "diverged", "failed")
# Consecutive rejected steps at the step limit that count as converged (`outcome`): the trust region has
# shrunk by about 4^-20 ~ 1e-12, no step of float64 size lowers the cost any more.
STALL_STEPS = 20

T = TypeVar("T")


def status(result) -> Int[Array, ...]:
    """Code of an Optimistix `sol.result` (batched or not, traced or not): `CONVERGED` (0), `MAX_STEPS` (1),
    `DIVERGED` (2, including non-finite values) or `FAILED` (3: a singular or broken-down linear solve)."""
    r = optx.RESULTS
    hit_max = (result == r.max_steps_reached) | (result == r.nonlinear_max_steps_reached)
    diverged = (result == r.nonlinear_divergence) | (result == r.nonfinite)
    return jnp.where(
        result == r.successful, CONVERGED, jnp.where(hit_max, MAX_STEPS, jnp.where(diverged, DIVERGED, FAILED))
    )


def outcome(sol: optx.Solution) -> Int[Array, ...]:
    """`status` of a solution, except that a trust-region least-squares fit (Gauss-Newton,
    Levenberg-Marquardt) that reached the step limit after `STALL_STEPS` rejected steps in a row counts as
    converged.

    Optimistix ends such a fit only on an accepted step whose change is below `rtol` / `atol`; at a
    minimum where float64 cannot resolve a smaller cost (a tolerance near 1e-9 on well-fitted data) every
    further step is rejected, and the fit runs to `max_steps` without moving. That is a converged fit, not
    an unconverged one (measured: the same value at 50, 200 and 800 steps, and `tol=1e-8` ends there).
    """
    code = status(sol.result)
    since = getattr(sol.state, "num_steps_since_acceptance", None)
    if since is None:  # minimisers (BFGS) keep no such count
        return code
    return jnp.where((code == MAX_STEPS) & (since >= STALL_STEPS), CONVERGED, code)


@dataclasses.dataclass(frozen=True)
class SolverReport:
    """The outcome codes of a method's fits, summed up (from `report`).

    Attributes:
        status: name of the worst outcome (`STATUS_NAMES`; "converged" when every fit converged).
        failed: fits that did not converge; total: fits checked.
        what: what one fit is, for the warning line ("anchor fits", "start fits", ...).
    """

    status: str
    failed: int
    total: int
    what: str = "fits"

    @property
    def converged(self) -> bool:
        """Whether every fit converged."""
        return self.failed == 0

    def params(self) -> dict:
        """The Result params entries: {"solver_status": name, "solver_failed": count}."""
        return {"solver_status": self.status, "solver_failed": self.failed}

    def warn(self, method: str, hint: str) -> bool:
        """One warning line (logger `jaxcal`) when a fit did not converge; True if so.

        Args:
            method: the method's name, first word of the line. hint: what the user can do about it.
        """
        if self.converged:
            return False
        logging.getLogger("jaxcal").warning(
            "%s: %d of %d %s did not converge (%s); reporting them as they stopped; %s",
            method,
            self.failed,
            self.total,
            self.what,
            self.status,
            hint,
        )
        return True


def report(codes, what: str = "fits") -> SolverReport:
    """Sum up outcome codes (any shape; from `outcome`) into a `SolverReport`."""
    c = np.asarray(codes, dtype=int).ravel()
    worst = int(c.max()) if c.size else CONVERGED
    return SolverReport(STATUS_NAMES[worst], int(np.count_nonzero(c != CONVERGED)), int(c.size), what)


def retry_unconverged(fit: Callable[[int], tuple[T, Array]], max_steps: int, factor: int = 4) -> tuple[T, Array, int]:
    """Run `fit(max_steps)`; when a fit stopped at the step limit, run it once more with `factor` times the steps.

    The retry starts afresh: a fit that converged the first time takes the same steps again and returns
    the same value, so the retry's output replaces the first one whole.

    Args:
        fit: max_steps -> (output, outcome codes from `outcome`, any shape).
        max_steps: the first step limit. factor: how many times more steps the retry gets.

    Returns:
        (output, codes, the step limit that produced them).
    """
    out, codes = fit(max_steps)
    if np.any(np.asarray(codes) == MAX_STEPS) and factor > 1:
        max_steps *= factor
        out, codes = fit(max_steps)
    return out, codes, max_steps


def _quiet(**_) -> None:
    """optx.BFGS's default `verbose`: print nothing."""


class StartedBFGS(optx.AbstractBFGS):
    """Optimistix's BFGS (Armijo backtracking, Newton descent on the inverse-Hessian approximation), started from
    a given inverse Hessian instead of the identity, for a flat parameter vector.

    Where the parameters have unlike scales (metres of an anchor, log-scales of a density) BFGS from the
    identity spends most of its steps learning the curvature; from the exact one (`newton_start`) its first step
    is Newton's and it converges in a few. It stops at the same minimum under the same tolerances.

    Attributes:
        rtol, atol: as for `optx.BFGS`. hessian_inv: (P, P) symmetric positive definite start. The rest (norm,
            descent, search) as `optx.BFGS`'s defaults.
    """

    rtol: float
    atol: float
    hessian_inv: Float[Array, "P P"]
    norm: Callable
    use_inverse: bool
    descent: optx.NewtonDescent
    search: optx.BacktrackingArmijo
    verbose: Callable

    def __init__(self, rtol: float, atol: float, hessian_inv: Float[Array, "P P"]):
        self.rtol, self.atol, self.hessian_inv = rtol, atol, hessian_inv
        self.norm, self.use_inverse = optx.max_norm, True
        self.descent = optx.NewtonDescent(linear_solver=lx.Cholesky())  # as optx.BFGS
        self.search = optx.BacktrackingArmijo()
        self.verbose = _quiet

    def init_hessian(self, y, f, grad):
        op = lx.PyTreeLinearOperator(self.hessian_inv, jax.eval_shape(lambda: y), lx.positive_semidefinite_tag)
        return optx.FunctionInfo.EvalGradHessianInv(f, grad, op), None


def newton_start(fn: Callable, y: Float[Array, " P"], args, floor: float = 1e-6) -> Float[Array, "P P"]:
    """The inverse of the exact Hessian of the scalar `fn(y, args)` at the flat `y`, made positive definite (absolute
    eigenvalues, floored at `floor` x the largest): the start of `StartedBFGS`, a Newton step where the Hessian
    is positive definite and a bounded step along a saddle or flat direction."""
    h = jax.hessian(fn)(y, args)
    ev, vec = jnp.linalg.eigh(0.5 * (h + h.T))
    ev = jnp.maximum(jnp.abs(ev), floor * jnp.max(jnp.abs(ev)))
    return (vec / ev) @ vec.T
