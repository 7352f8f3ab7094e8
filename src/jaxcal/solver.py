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

import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Int

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
