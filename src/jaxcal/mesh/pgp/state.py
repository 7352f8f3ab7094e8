"""The filter's pytrees: static configuration, numeric parameters, inputs, the scan's state and its
per-epoch outputs, the inspection grids (`PGPInfo`), and the state's construction and full-grid view."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from jaxcal.mesh import fast as F
from jaxcal.mesh import grid as G

__all__ = [
    "FilterConfig",
    "FilterParams",
    "FilterInputs",
    "FilterState",
    "FilterOut",
    "PGPInfo",
    "init_state",
    "full_logpost",
    "full_state",
]


class FilterConfig(eqx.Module):
    """Static part of the filter (shapes and modes): changing it recompiles."""

    grid: G.Grid = eqx.field(static=True)
    top_k: int = eqx.field(static=True)
    n_hyp: int = eqx.field(static=True)
    update_order: str = eqx.field(static=True)
    smoothing: str = eqx.field(static=True)
    median_window: int = eqx.field(static=True)
    mode: str = eqx.field(static=True)  # "pgp" (hypotheses, eq. 10-11) or "parametric" (eq. 9)
    n_snap: int = eqx.field(static=True)
    likelihood: str = eqx.field(static=True, default="direct")
    # "hard": eq. (10) as written; "soft": `G.soft_hypotheses` with `FilterParams.tau_temp` (tuning)
    select: str = eqx.field(static=True, default="hard")
    remat: bool = eqx.field(static=True, default=False)  # jax.checkpoint the epoch (gradients)
    # W of the windowed epochs (`fast.py`); 0: every epoch on the full grid
    window: int = eqx.field(static=True, default=0)
    # W of the small windows tried first (`window_small_m`); 0: none
    window_small: int = eqx.field(static=True, default=0)
    # range kernel of eq. (11): "gaussian" or "mixture" (`grid.range_kernel_log`)
    range_model: str = eqx.field(static=True, default="gaussian")


class FilterParams(eqx.Module):
    """Numeric parameters as arrays: changing them does not recompile."""

    tau: Float[Array, ""]
    r_est: Float[Array, ""]
    sigma_r: Float[Array, ""]
    v: Float[Array, ""]
    sigma_v: Float[Array, ""]
    alpha: Float[Array, ""]
    p_out: Float[Array, ""]
    nlos_weight: Float[Array, ""]
    nlos_mean_m: Float[Array, ""]
    tau_temp: Float[Array, ""] | None = None  # temperature of `select="soft"` (unused when hard)


class FilterInputs(eqx.Module):
    """Per-dataset arrays, nodes in filter order (a0, a1, a2, others)."""

    z: Float[Array, "epochs nodes nodes"]  # symmetric ranges [m], NaN missing
    dt: Float[Array, " epochs"]  # time step to the previous epoch [s] (0 first)
    mask: Bool[Array, "nodes nx ny"]  # allowed cells per node
    allowed: Bool[Array, "nodes nodes"]  # structural neighbour sets (eq. 5, 6, 11)
    need: Float[Array, " nodes"]  # localised neighbours required
    snap_at: Float[Array, " snaps"]  # epochs whose posteriors are kept


class FilterState(eqx.Module):
    """What `lax.scan` carries from one epoch to the next."""

    logpost: Float[Array, "nodes nx ny"]
    heard: Bool[Array, "nodes nodes"]
    smooth: Float[Array, "nodes 2"]
    started: Bool[Array, " nodes"]
    buf: Float[Array, "nodes window 2"]
    snaps: Float[Array, "snaps nodes nx ny"]
    # windowed representation (`fast.py`): while `windowed`, the posteriors are `win` placed at
    # `org` (and `logpost` is stale); `bound`: log of the largest value outside each window
    win: Float[Array, "nodes w w"]
    org: Array  # (nodes, 2) int32 window origins
    bound: Float[Array, " nodes"]
    windowed: Bool[Array, ""]
    # a1 (filter node 1) lives on one grid row (eq. 5): while windowed, its posterior is this whole
    # row (n cells, exact, no bound needed; its 1-D tail is too wide for a square window)
    row: Float[Array, " n"]
    # whether the next windowed epoch tries the small window (`FilterConfig.window_small`) first
    small: Bool[Array, ""]


class FilterOut(eqx.Module):
    """Per-epoch outputs of the scan."""

    estimate: Float[Array, "nodes 2"]  # after optional smoothing; NaN when not localised
    raw: Float[Array, "nodes 2"]  # eq. (13) before smoothing; NaN when not localised
    log_mass: Float[Array, " nodes"]  # log of the posterior's total mass (0 when normalised)
    # log normaliser of eq. (12): log sum_g prior(g) * eq.11(g), prior normalised, factors as in
    # eq. (11) (without the Gaussian's constant); 0 for a node without factors this epoch
    log_evidence: Float[Array, " nodes"]
    n_factors: Float[Array, " nodes"]  # number of range factors in eq. (11) this epoch
    windowed: Bool[Array, ""]  # whether this epoch ran on the windows (`likelihood="window"`)
    small: Bool[Array, ""]  # whether it ran on the small windows (`window_small_m`)


class PGPInfo(eqx.Module):
    """Posterior grids for inspection (multimodality), nodes in the dataset's order.

    Attributes:
        axis_m: (n,) cell-centre coordinates of both grid axes [m] (config frame).
        posterior: (N, n, n) final posterior probabilities, `posterior[i, ix, iy]` at
            `(axis_m[ix], axis_m[iy])`.
        snapshot_epochs: (S,) epochs of `snapshots`. snapshots: (S, N, n, n) posteriors at those
            epochs.
        log_mass: (K, N) log of the posterior mass after each epoch's update (0 up to rounding).
        raw_track: (K, N, 2) eq. (13) estimates before smoothing [m].
        localised: (N,) whether each node became localised.
        offset_m: the range offset subtracted from every range before the filter ran [m] (`bias`; 0 when
            none was fitted, NaN when the fit had too few pairs and none was subtracted).
        frame: the frame of `axis_m` and the grids, `anchors:b0,b1,b2`: the configuration's own, or
            the proxy frame the filter ran in (`PGPParams.frame`; the result is in the configuration's).
    """

    axis_m: np.ndarray
    posterior: np.ndarray
    snapshot_epochs: np.ndarray
    snapshots: np.ndarray
    log_mass: np.ndarray
    raw_track: np.ndarray
    localised: np.ndarray
    frame: str = eqx.field(static=True, default="")
    offset_m: float = eqx.field(static=True, default=0.0)


def full_logpost(config: FilterConfig, state: FilterState) -> Float[Array, "nodes nx ny"]:
    """(nodes, nx, ny) log posteriors of `state` on the full grid (windows placed on `-inf` when windowed)."""
    if not config.window:
        return state.logpost
    full = jax.vmap(F.scatter_window, in_axes=(0, 0, None))(state.win, state.org, config.grid.n_side)
    c = config.grid.n_half
    full = full.at[1].set(jnp.full_like(full[1], -jnp.inf).at[:, c].set(state.row))
    return jnp.where(state.windowed, full, state.logpost)


def init_state(config: FilterConfig, logpost0: Float[Array, "nodes nx ny"]) -> FilterState:
    """The filter's state before the first epoch, from (nodes, nx, ny) initial log posteriors
    (`prepare`'s: uniform over each node's region)."""
    n = logpost0.shape[0]
    w = config.window or 1
    dtype = logpost0.dtype
    nan2 = jnp.full((n, 2), jnp.nan, dtype)
    return FilterState(
        logpost=logpost0,
        heard=jnp.zeros((n, n), bool),
        smooth=nan2,
        started=jnp.zeros((n,), bool),
        buf=jnp.full((n, config.median_window, 2), jnp.nan, dtype),
        snaps=jnp.full((config.n_snap,) + logpost0.shape, -jnp.inf, dtype),
        win=jnp.zeros((n, w, w), dtype),
        org=jnp.zeros((n, 2), jnp.int32),
        bound=jnp.full((n,), jnp.inf, dtype),
        windowed=jnp.asarray(False),
        row=jnp.full((config.grid.n_side,), -jnp.inf, dtype),
        small=jnp.asarray(True),
    )


def full_state(config: FilterConfig, state: FilterState) -> FilterState:
    """`state` with its full-grid `logpost` (windows placed on the grid), not windowed."""
    return dataclasses.replace(state, logpost=full_logpost(config, state), windowed=jnp.asarray(False))
