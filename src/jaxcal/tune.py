"""Differentiable tuning of the PGP filter's sigma_r, sigma_v and tau (Optimistix BFGS, scan).

The filter of `jaxcal.mesh.pgp` is differentiable in its numeric parameters except for the hard
hypothesis cut of eq. (10), whose derivative in `tau` is zero almost everywhere. Tuning thus runs
the filter with `select="soft"`: cell l of a node's sorted cells is weighted by
`sigmoid((tau - m_l) / tau_temp)`, `m_l` the probability mass before it (`grid.soft_hypotheses`; the
hard rule is the limit `tau_temp -> 0`). The parameters are optimised unconstrained as
`theta = (log sigma_r, log sigma_v, logit tau)`, and with `range_model="mixture"` also
`(logit nlos_weight, log nlos_mean_m)` of the NLOS-aware range kernel (`grid.range_kernel_log`).

Objectives (both per tuning window, the first `epochs` epochs of the dataset):

- `truth`: RMSE [m] of the final positions (a0 excluded) against the ground truth in the
  configuration frame, each position the tempered eq. (13) estimate of `soft_estimates` (a grid
  posterior collapses into one cell, where eq. 13 itself is piecewise constant: zero gradient).
- `evidence`: negative log predictive likelihood of the measured ranges, in nats per range factor.
  Per epoch and node, before the update, the log normaliser of eq. (12), `log sum_g pbar(g) L(g)`
  (`FilterOut.log_evidence`), with each eq. (11) factor read as a density of the range z on [0, L]:
  `f(z | g) = ((1 - p_out) sum_l w_l exp(-(|g - g_l| - z)^2 / 2 sigma_r^2) + p_out) / Z`,
  `Z = (1 - p_out) sigma_r sqrt(2 pi) + p_out L`, L = the grid's diagonal (the longest range it
  can explain). This is the filter's own factor up to a constant in z, so the filter's posterior is
  exactly the one this density model implies; with `p_out = 0` it is the Gaussian of eq. (11). The
  mixture kernel is scaled to the same integral `sigma_r sqrt(2 pi)`, so Z holds for it too. No
  ground truth is needed. (Nodes update independently given the others' hypotheses, so the sum over
  nodes is a pseudo-likelihood; every pair's range enters once per end.)

Memory: reverse mode through `lax.scan` keeps the carry of every epoch, `(epochs, nodes, cells)`
log posteriors (12 nodes x 63^2 cells x 200 epochs x 8 B = 76 MB for torgau at 1 m cells), and with
`FilterConfig.remat` each epoch's intermediates are recomputed in the backward pass, not stored
(without it the eq. (11) intermediates take gigabytes). Defaults: 1.0 m cells, 200 epochs, float64.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from jaxcal.data import MeshDataset
from jaxcal.errors import JaxcalError
from jaxcal.mesh import grid as G
from jaxcal.mesh import pgp
from jaxcal.mesh.frame import to_frame
from jaxcal.params import with_overrides

__all__ = [
    "OBJECTIVES",
    "TUNED",
    "TuneResult",
    "window",
    "truth_in_filter_order",
    "track_rmse",
    "final_rmse",
    "neg_log_predictive",
    "Problem",
    "make_problem",
    "objective",
    "tune",
]

OBJECTIVES = ("truth", "evidence")
TUNED = ("sigma_r", "sigma_v", "tau")
# tuned as well when range_model="mixture" (theta entries 3 and 4)
TUNED_MIXTURE = ("nlos_weight", "nlos_mean_m")
_LOGIT = ("tau", "nlos_weight")  # in (0, 1); the others are positive (log)


def tuned_names(range_model: str) -> tuple[str, ...]:
    """Names of theta's entries, in order, for a range model."""
    return TUNED + (TUNED_MIXTURE if range_model == "mixture" else ())


def window(dataset: MeshDataset, epochs: int | None) -> MeshDataset:
    """The first `epochs` epochs of a mesh dataset (all of them when None or larger)."""
    if epochs is None or epochs >= dataset.n_epochs:
        return dataset
    if epochs < 1:
        raise JaxcalError(f"epochs: must be >= 1, got {epochs}")
    k = int(epochs)
    opt = {
        f: getattr(dataset, f)[:k]
        for f in ("fp_rssi", "rx_rssi")
        if getattr(dataset, f) is not None
    }
    return dataclasses.replace(dataset, time=dataset.time[:k], range=dataset.range[:k], **opt)


def truth_in_filter_order(
    dataset: MeshDataset, config: str | None, order: np.ndarray
) -> np.ndarray:
    """(N, 2) true positions in the configuration frame, rows in filter order; NaN when unknown.

    As `metrics.truth_in_result_frame`: the frame is built in 3-D when the truth is 3-D, then x, y.
    """
    n = dataset.n_nodes
    if dataset.truth is None:
        return np.full((n, 2), np.nan)
    a0, a1, a2 = dataset.config(config)
    t = dataset.truth
    if not np.isfinite(t[[a0, a1, a2]]).all():
        return np.full((n, 2), np.nan)
    return to_frame(t, a0, a1, a2)[:, :2][order]


def track_rmse(
    est: Float[Array, "epochs nodes 2"], truth: Float[Array, "nodes 2"]
) -> Float[Array, ""]:
    """RMSE [m] over every finite (epoch, node) estimate except node 0 (a0) with a known truth.

    Differentiable: missing estimates are replaced before squaring, so their NaN never reaches a
    gradient. NaN when no estimate counts.
    """
    ok = jnp.isfinite(est).all(-1) & jnp.isfinite(truth).all(-1)[None, :]
    ok = ok.at[:, 0].set(False)
    t = jnp.where(jnp.isfinite(truth), truth, 0.0)
    e = jnp.where(ok[..., None], est, t[None]) - t[None]
    cnt = jnp.sum(ok)
    mse = jnp.sum(e * e) / jnp.maximum(cnt, 1)
    return jnp.where(cnt > 0, jnp.sqrt(jnp.where(cnt > 0, mse, 1.0)), jnp.nan)


def final_rmse(
    est: Float[Array, "epochs nodes 2"], truth: Float[Array, "nodes 2"]
) -> Float[Array, ""]:
    """RMSE [m] of the last epoch's estimates, a0 excluded (`final_rmse_m` of `jaxcal evaluate`)."""
    return track_rmse(est[-1:], truth)


def neg_log_predictive(
    out: pgp.FilterOut, sigma_r: Float[Array, ""], p_out: Float[Array, ""], span_m: float
) -> Float[Array, ""]:
    """Negative log predictive likelihood of the ranges [nats per range factor] (module docstring).

    Args:
        out: per-epoch filter outputs (`log_evidence`, `n_factors` of shape (K, N)).
        sigma_r: range std [m]. p_out: floor weight. span_m: L, support of the range density [m].

    Returns:
        `-(sum log_evidence - n_factors log Z) / sum n_factors`; NaN when no range was used.
    """
    log_z = jnp.log((1.0 - p_out) * sigma_r * math.sqrt(2 * math.pi) + p_out * span_m)
    n = jnp.sum(out.n_factors)
    total = jnp.sum(out.log_evidence) - n * log_z
    return jnp.where(n > 0, -total / jnp.maximum(n, 1.0), jnp.nan)


class Problem(eqx.Module):
    """Everything the objective needs besides theta (the filter's config is static)."""

    cfg: pgp.FilterConfig
    prm: pgp.FilterParams
    inp: pgp.FilterInputs
    logpost0: Float[Array, "nodes nx ny"]
    truth: Float[Array, "nodes 2"]
    est_temp: Float[Array, ""]
    span_m: float = eqx.field(static=True)
    kind: str = eqx.field(static=True)


def grid_span_m(cfg: pgp.FilterConfig) -> float:
    """L of the evidence density: the longest distance between two cells of the grid [m]."""
    return 2.0 * math.sqrt(2.0) * cfg.grid.n_half * cfg.grid.cell_m


def make_problem(
    dataset: MeshDataset,
    params: pgp.PGPParams,
    config: str | None,
    kind: str,
    tau_temp: float = 0.05,
    remat: bool = True,
    est_temp: float = 10.0,
) -> tuple[Problem, np.ndarray]:
    """Prepare the filter for tuning (soft hypothesis cut, rematerialised epochs).

    Args:
        dataset: the (windowed) mesh dataset. params: filter parameters (the start point).
        config: frame configuration name. kind: "truth" or "evidence".
        tau_temp: temperature of the soft cut (mass units; 0 gives the hard rule, not differentiable
            in tau). remat: checkpoint every epoch (memory ~ epochs x carry).
        est_temp: temperature of the `truth` objective's estimate (`soft_estimates`, nats).

    Returns:
        (Problem, order): `order[k]` is the dataset index of filter node k.
    """
    if kind not in OBJECTIVES:
        raise JaxcalError(f"objective: one of {', '.join(OBJECTIVES)}; got {kind!r}")
    cfg, prm, inp, lp0, order = pgp.prepare(dataset, params, config, "pgp")
    ftype = lp0.dtype
    select = "soft" if tau_temp > 0 else "hard"
    cfg = dataclasses.replace(cfg, select=select, remat=remat)
    prm = dataclasses.replace(prm, tau_temp=jnp.asarray(max(tau_temp, 1e-12), ftype))
    truth = truth_in_filter_order(dataset, config, order)
    if kind == "truth" and not np.isfinite(truth[1:]).any():
        raise JaxcalError(
            f"{dataset.name}: objective 'truth' needs ground truth (use --objective evidence)"
        )
    prob = Problem(
        cfg,
        prm,
        inp,
        lp0,
        jnp.asarray(truth, ftype),
        jnp.asarray(est_temp, ftype),
        grid_span_m(cfg),
        kind,
    )
    return prob, order


def _with_theta(prm: pgp.FilterParams, theta: Float[Array, " p"]) -> pgp.FilterParams:
    names = (TUNED + TUNED_MIXTURE)[: theta.shape[0]]
    return dataclasses.replace(
        prm,
        **{
            k: jax.nn.sigmoid(theta[i]) if k in _LOGIT else jnp.exp(theta[i])
            for i, k in enumerate(names)
        },
    )


def theta_of(
    sigma_r: float,
    sigma_v: float,
    tau: float,
    dtype=None,
    nlos_weight: float | None = None,
    nlos_mean_m: float | None = None,
) -> Float[Array, " p"]:
    """Unconstrained parameters (log sigma_r, log sigma_v, logit tau[, logit nlos_weight,
    log nlos_mean_m]); the last two only when `nlos_weight` is given."""

    def logit(u):
        u = min(max(u, 1e-6), 1 - 1e-6)
        return math.log(u / (1 - u))

    t = [math.log(sigma_r), math.log(sigma_v), logit(tau)]
    if nlos_weight is not None:
        t += [logit(nlos_weight), math.log(nlos_mean_m)]
    return jnp.asarray(t, dtype)


def values_of(theta) -> dict[str, float]:
    """{sigma_r, sigma_v, tau[, nlos_weight, nlos_mean_m]} of unconstrained parameters."""
    t = np.asarray(theta, dtype=np.float64)
    names = (TUNED + TUNED_MIXTURE)[: t.shape[0]]
    return {
        k: float(1.0 / (1.0 + np.exp(-t[i])) if k in _LOGIT else np.exp(t[i]))
        for i, k in enumerate(names)
    }


def objective(theta: Float[Array, " p"], prob: Problem) -> Float[Array, ""]:
    """Objective at theta (`theta_of`): RMSE [m] or NLPL [nats]."""
    prm = _with_theta(prob.prm, theta)
    st, out = pgp._filter(prob.cfg, prm, prob.inp, prob.logpost0)
    if prob.kind == "truth":
        radius = jnp.maximum(prm.r_est, 1.5 * prob.cfg.grid.cell_m)
        est = soft_estimates(
            st.logpost, prob.cfg.grid.cells(st.logpost.dtype), radius, prob.est_temp
        )
        loc = jnp.isfinite(out.estimate[-1]).all(-1)
        est = jnp.where(loc[:, None], est, jnp.nan)
        return final_rmse(est[None], prob.truth)
    return neg_log_predictive(out, prm.sigma_r, prm.p_out, prob.span_m)


def soft_estimates(
    logpost: Float[Array, "nodes nx ny"], cells: Float[Array, "cells 2"], r_est, est_temp
) -> Float[Array, "nodes 2"]:
    """Eq. (13) on the tempered posterior `p^(1 / est_temp)` (est_temp = 1: eq. 13 itself) [m].

    A grid posterior after many epochs sits in one cell, so eq. (13) is piecewise constant in the
    parameters (zero gradient); tempering spreads the window weights over the neighbouring cells by
    their log-posterior differences, a sub-cell estimate that moves smoothly with the parameters.
    The `truth` objective uses a window of at least 1.5 cells (the 3 x 3 cells around the MLE).
    """
    lp = logpost.reshape(logpost.shape[0], -1)
    return jax.vmap(G.window_estimate, in_axes=(0, None, None))(lp / est_temp, cells, r_est)


@eqx.filter_jit
def _minimise(theta0, prob: Problem, rtol: float, atol: float, max_steps: int):
    solver = optx.BFGS(rtol=rtol, atol=atol)
    return optx.minimise(objective, solver, theta0, args=prob, max_steps=max_steps, throw=False)


_value = eqx.filter_jit(objective)


def _hard_metrics(theta, prob: Problem) -> dict[str, float]:
    """RMSE, final RMSE, NLPL with the hard cut of eq. (10) (what `calibrate` runs)."""
    prm = _with_theta(prob.prm, theta)
    cfg = dataclasses.replace(prob.cfg, select="hard", remat=False)
    _, out = pgp.run_filter(cfg, prm, prob.inp, prob.logpost0)
    return {
        "rmse_m": float(track_rmse(out.estimate, prob.truth)),
        "final_rmse_m": float(final_rmse(out.estimate, prob.truth)),
        "nlpl": float(neg_log_predictive(out, prm.sigma_r, prm.p_out, prob.span_m)),
    }


@dataclasses.dataclass(frozen=True)
class TuneResult:
    """Outcome of `tune`.

    Attributes:
        params: the fitted values {sigma_r [m], sigma_v [m per epoch], tau} (plus nlos_weight,
            nlos_mean_m [m] with the mixture range model).
        start: the start values (same keys).
        objective: "truth" or "evidence".
        before, after: objective value (soft cut) at the start and the end.
        hard_before, hard_after: {rmse_m, final_rmse_m, nlpl} with the hard cut on the window.
        steps: optimiser steps. converged: whether Optimistix reports success. message: its result.
        settings: window and grid used {epochs, cell_m, n_cells_side, tau_temp, dtype}.
    """

    params: dict
    start: dict
    objective: str
    before: float
    after: float
    hard_before: dict
    hard_after: dict
    steps: int
    converged: bool
    message: str
    settings: dict


def tune(
    dataset: MeshDataset,
    params: pgp.PGPParams | dict | None = None,
    config: str | None = None,
    *,
    objective_name: str = "truth",
    epochs: int | None = 200,
    tau_temp: float = 0.05,
    max_steps: int = 30,
    rtol: float = 1e-3,
    atol: float = 1e-4,
) -> TuneResult:
    """Fit sigma_r, sigma_v and tau (and with `range_model="mixture"` nlos_weight and
    nlos_mean_m) of the PGP filter by BFGS on the tuning objective.

    Args:
        dataset: a mesh dataset (ground truth needed for `objective_name="truth"`).
        params: start point and fixed parameters (`PGPParams` or overrides; `cell_m` sets the grid).
        config: frame configuration name.
        objective_name: "truth" (RMSE [m]) or "evidence" (NLPL [nats per range]).
        epochs: tuning window, the first `epochs` epochs (None: all).
        tau_temp: temperature of the soft cut of tau. max_steps, rtol, atol: BFGS settings.

    Returns:
        A `TuneResult`; the fitted values go into `jaxcal calibrate --params`.
    """
    if not isinstance(params, pgp.PGPParams):
        params = with_overrides(pgp.PGPParams(), params)
    if dataset.n_epochs == 0:
        raise JaxcalError(f"{dataset.name}: no epochs to tune on")
    ds = window(dataset, epochs)
    prob, _ = make_problem(ds, params, config, objective_name, tau_temp)
    dtype = prob.logpost0.dtype
    mix = params.range_model == "mixture"
    theta0 = theta_of(
        params.sigma_r, params.sigma_v, params.tau, dtype,
        nlos_weight=params.nlos_weight if mix else None,
        nlos_mean_m=params.nlos_mean_m,
    )
    before = float(_value(theta0, prob))
    if not math.isfinite(before):
        raise JaxcalError(
            f"{dataset.name}: the objective is undefined at the start (no node localised?)"
        )
    sol = _minimise(theta0, prob, rtol, atol, max_steps)
    theta = sol.value
    after = float(_value(theta, prob))
    if not math.isfinite(after) or after > before:  # never hand back a worse point than the start
        theta, after = theta0, before
    ok = sol.result == optx.RESULTS.successful
    return TuneResult(
        params=values_of(theta),
        start=values_of(theta0),
        objective=objective_name,
        before=before,
        after=after,
        hard_before=_hard_metrics(theta0, prob),
        hard_after=_hard_metrics(theta, prob),
        steps=int(sol.stats["num_steps"]),
        converged=bool(ok),
        message="successful" if ok else str(optx.RESULTS[sol.result]).split(".")[0],
        settings={
            "epochs": ds.n_epochs,
            "cell_m": params.cell_m,
            "n_cells_side": prob.cfg.grid.n_side,
            "tau_temp": tau_temp,
            "dtype": str(dtype),
            "rtol": rtol,
            "atol": atol,
            "max_steps": max_steps,
        },
    )
