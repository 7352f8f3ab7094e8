"""PGP: the grid-based Bayesian self-calibration filter of paper 000 (Section III, eq. 3-14).

Nodes are reordered so that the configuration's (a0, a1, a2) come first. Every node has a log
posterior
on one common square grid (`grid.py`), all of them one batched array `(nodes, nx, ny)`; a0 is the
origin
cell, a1's region is the positive x axis (the 1-D histogram of eq. 5), a2's the half plane y >= 0
(eq. 6). Per epoch and node: motion update over the `top_k` most probable cells (eq. 7-8), the
hypothesis-weighted likelihood of every neighbour with a range (eq. 10-11), the posterior in log
space
(eq. 12), the estimate within `r_est` of the MLE cell (eq. 13), optional smoothing (eq. 14). Epochs
run
in one `lax.scan` inside one jitted function; numbers are arrays, so changing them never recompiles.

Choices the paper leaves open (documented here, recorded in the result's `params`):

- Ranges: the mean of i->j and j->i when both exist, else the one that exists; missing = no factor.
- Neighbours: a1 uses a0 only (eq. 5), a2 uses a0 and a1 (eq. 6; `a2_all=True` lets it use every
node),
  the others every node. A neighbour contributes hypotheses only once it is *localised*: it has
  received
  ranges from at least `min_refs` distinct localised neighbours (a1: a0; a2: a0 and a1), so a node
  whose posterior is still a ring around one reference does not spread a random arc of that ring as
  hypotheses. A node's estimate is reported (available) from the epoch it is localised.
- Motion update only for localised nodes; before that the posterior accumulates likelihoods exactly
  (a static prior), because truncating a ring to `top_k` cells would lock in a random arc.
- Hypotheses: the smallest set of most probable cells holding mass `tau`, capped at `max_hyp` cells.
- `sigma_v` is the std of the transition distance of eq. (8) in metres per epoch; `v * dt` with dt
the
  epoch time step.
- `update_order`: "jacobi" (default) updates every node from the previous epoch's posteriors: the
  result does not depend on node labels. "gauss-seidel" updates a1, a2, then the others in index
  order,
  each using the newest posteriors of the nodes before it (order-dependent, localises in fewer
  epochs).

Beyond the paper (issue #18): when a frame pair (a0-a1, a0-a2, a1-a2) is never measured, or only late,
the paper's rule never localises a1 (or a2) and hence nothing after it, although the network may fix
every node. `frame="auto"` (default) then runs the filter in the frame of the best-connected,
best-conditioned triple whose pairs are measured (`identify.filter_frame`) and moves every epoch's
estimates into the configuration's frame through that epoch's a0, a1, a2 estimates (the final
covariance to first order, `frame.frame_covariance`); `PGPInfo.frame` names the grids' frame. Where the
configuration's pairs are measured early the filter is the paper's, unchanged. `calibrate` then sets the
nodes the measured graph cannot fix (`identify.py`) to NaN rows, with one warning line.

Defaults (`PGPParams`): 0.5 m cells, at most 8 hypotheses, `likelihood="window"`: the fast path
of `fast.py`. Until every node is localised (the first few epochs) and whenever the mass could
leave a window, an epoch is the direct evaluation on every cell; otherwise every node's epoch runs
on a W x W window around its mass (10 m a side) and a1 on its row, with a proven bound (< e^-30)
on the posterior mass outside, so the answers equal the direct evaluation (`likelihood="direct"`,
kept as the reference) up to rounding. `run_pgp` drives the scan from the host in chunks
(`run_chunked`): windowed chunks do not carry the full grid. `_filter` (one scan, used by tuning
and sweeps) computes the same epochs. Speed: `benchmarks/pgp_speed.py` (figures on the benchmarks
page of the docs, "PGP speed").
`start`/`advance` feed epochs as they arrive (live calibration); chunks equal one run.

Large sites (issue #26): the one grid grows with the site's area, so at constant density its cost
grows as N^2 and `extent_m` cuts off nodes beyond 60 m. `grid_mode="auto"` (default) runs such sites
(the full grid wider than one node-local grid, i.e. the site wider than radio range) on node-local grids
(`local.py`): the same epochs where each node's mass lies in its own grids (tested), at a cost that
follows the measured pairs, with a stricter localisation rule (`localise_m`). Sites within radio range
(torgau and the other small recordings) run on the one grid as before.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from jaxcal.data import MeshDataset, Result
from jaxcal.errors import JaxcalError
from jaxcal.mesh import fast as F
from jaxcal.mesh import grid as G
from jaxcal.mesh import local as L
from jaxcal.params import as_dict, with_overrides

__all__ = [
    "PGPParams",
    "PGPInfo",
    "PGPStream",
    "run_pgp",
    "calibrate",
    "start",
    "advance",
    "stream_posterior",
    "symmetric_ranges",
    "validate_params",
    "run_filter",
    "uses_local",
    "global_grid_only",
]


class PGPParams(eqx.Module):
    """Parameters of the PGP filter and of the parametric baseline (defaults documented per field).

    Attributes:
        cell_m: grid cell size [m] (0.5: fine enough for sub-metre results, coarse enough to
            finish).
        extent_m: cap on the grid half-width R [m] (R from `extent_radius`, see `grid.py`).
        margin_m: added to the farthest chain of median ranges from a0 when sizing the grid [m].
        top_k: K of eq. (7), cells carried through the motion update.
        tau: probability-mass fraction of eq. (10) taken as hypotheses.
        max_hyp: cap on the number of hypotheses per neighbour (8: a localised posterior at 0.5 m
            cells holds > 90 % of its mass in fewer cells; the cap bounds the cost of eq. 11).
        r_est: radius of the estimation window around the MLE cell, eq. (13) [m].
        sigma_r: ranging standard deviation [m] (LOS 1-sigma quantile of the paper's Table I).
        v: expected node speed [m/s] (0: static nodes).
        sigma_v: transition standard deviation of eq. (8) [m per epoch]; > 0 lets the filter
            recover.
        alpha: smoothing factor of eq. (14) in (0, 1].
        smoothing: "none", "ema" or "median-ema" (median of the last `median_window` estimates,
            then EMA).
        median_window: window of the median in "median-ema" [epochs].
        update_order: "jacobi" or "gauss-seidel" (see the module docstring).
        min_refs: localised neighbours a node must have heard before it counts as localised.
        a2_all: let a2 use every localised node, not only a0 and a1 (eq. 6 uses a0 and a1).
        p_out: robust floor of each likelihood factor, `(1 - p_out) * eq.11-factor + p_out` (0: the
            paper's eq. 11 exactly). Default 0.05: with heavy-tailed NLOS ranges a pure Gaussian
            factor
            lets one outlier ring outvote the others (simulated torgau conf1, 200 epochs: RMSE 2.97
            m at
            0 and 2.58 m at sigma_r = 1, 0.29 m at p_out = 0.05).
        likelihood: how eq. (11) is evaluated (same answer, different cost):
            "window" (default; the fast path of `fast.py`): once every node is localised, every
            node's epoch runs on a W x W window of cells around its probability mass, with a proven
            bound on the mass outside (below e^-30, else that epoch runs on the full grid);
            "direct" (the reference: every cell, neighbours without a range skipped in a loop;
            "sparse" is an alias); "dense" (every pair and hypothesis vmapped, then masked).
        window_m: side of the window of `likelihood="window"` [m] (10 m: covers the 32 most
            probable cells plus the tail of the motion kernel at sigma_v = 0.25 m, and a2's wider
            posterior (two ranges only; how often each size holds: the benchmarks page); a window
            too small for the data only makes more epochs fall back to the full grid, never
            changes the answer).
        window_small_m: side of the smaller window tried first [m] (0: none). An epoch runs on it
            when its own proven bound holds for every node, else on the `window_m` window, else
            on the full grid (each fallback re-runs the epoch, answers unchanged). 7 m: the bound
            needs ~2.6 m of motion-kernel tail (sigma_v = 0.25 m) around the top_k cells.
        range_model: the range kernel of eq. (11): "gaussian" (the paper) or "mixture" (NLOS-aware,
            `grid.range_kernel_log`: a LOS Gaussian of std sigma_r plus, with weight
            `nlos_weight`, the Gaussian convolved with a positive exponential of mean
            `nlos_mean_m`, so ranges longer than the geometry are explained as NLOS while short
            ones stay unlikely; `p_out` still adds the uniform floor).
        nlos_weight: NLOS share of the mixture in [0, 1) (only with range_model="mixture").
            Default 0.2: the paper's Table I has ~24 % NLOS ranges in its hall.
        nlos_mean_m: mean NLOS excess range [m] of the mixture (default 1 m: Table I's NLOS
            median error 0.69 m; its mean 3.78 m is driven by rare long outliers, which `p_out`
            covers).
        frame: which frame the filter runs in (`identify.filter_frame`): "auto" (default) the
            configuration's own when its three pairs are measured early (the paper's rule), else the
            best-connected triple, the track then moved into the configuration's frame epoch by
            epoch; "direct": always the configuration's own (the paper; a1 without a range to a0
            is never placed, nor anything after it); "proxy": always the best-connected triple.
        grid_mode: where the posteriors live: "global" (one square grid around a0 for every node,
            half-width from the ranges capped by `extent_m`), "local" (node-local grids, `local.py`:
            cost about pairs x window cells whatever the site's size, no `extent_m` cap; jacobi order,
            `likelihood="window"` and mode "pgp" only, else the global grid), or "auto" (default): local
            when the global grid would be wider than one node-local grid (sites larger than radio range),
            so small sites run as before.
        local_m: side of a node-local wide grid [m] (0, default: twice the longest per-pair median range
            plus `margin_m` and 1 m, so the ring of any range lies inside).
        localise_m: node-local grids only: a node counts as localised once it has heard `min_refs`
            localised neighbours *and* its posterior holds 99 % of its mass within `localise_m` [m] of
            its most probable cell (2 m; 0: `min_refs` alone, as on the global grid). Three rings from
            nearby nodes can leave two mirror modes; the motion update's `top_k` cells then lock onto
            one of them (N = 100, seed 0: 2 to 7 of 100 nodes 47-50 m off without this rule).
        bias: the common range offset c (antenna delays, LOS excess delay): "none" (the paper: ranges
            taken as unbiased), "network" (a first run on the first `OFFSET_EPOCHS` epochs, then c fitted
            jointly with positions to the per-pair medians, `range_offset.fit_offset`, and the filter run
            on the ranges minus c; `PGPInfo.offset_m`), or "auto" (default): "network" where the node-local
            grids run (`grid_mode`), "none" on the global grid. An unmodelled offset becomes a scale error
            that grows with the site's extent (N = 100: 0.53 -> 0.27 m aligned RMSE, docs' large networks
            page); small sites keep the paper's filter bit for bit.
    """

    cell_m: float = 0.5
    extent_m: float = 60.0
    margin_m: float = 2.0
    top_k: int = 32
    tau: float = 0.9
    max_hyp: int = 8
    r_est: float = 1.0
    sigma_r: float = 0.3
    v: float = 0.0
    sigma_v: float = 0.25
    alpha: float = 0.2
    smoothing: str = "none"
    median_window: int = 9
    update_order: str = "jacobi"
    min_refs: int = 3
    a2_all: bool = False
    p_out: float = 0.05
    likelihood: str = "window"
    window_m: float = 10.0
    window_small_m: float = 7.0
    range_model: str = "gaussian"
    nlos_weight: float = 0.2
    nlos_mean_m: float = 1.0
    frame: str = "auto"
    grid_mode: str = "auto"
    local_m: float = 0.0
    localise_m: float = 2.0
    bias: str = "auto"


BIASES = ("auto", "none", "network")
# epochs of the first run that `bias="network"` fits the range offset from (the posteriors settle within
# ~20 epochs at the defaults; N = 100 seed 0 fits the same c to 1e-6 m from 50 epochs as from 200)
OFFSET_EPOCHS = 50
GRID_MODES = ("auto", "global", "local")
FRAMES = ("auto", "direct", "proxy")
LIKELIHOODS = ("window", "direct", "sparse", "dense")
RANGE_MODELS = ("gaussian", "mixture")
# PGPParams fields that are arrays in `FilterParams` (sweeps and tuning change them without
# recompiling), in FilterParams' order
NUMERIC = ("tau", "r_est", "sigma_r", "v", "sigma_v", "alpha", "p_out", "nlos_weight", "nlos_mean_m")


def validate_params(p: PGPParams) -> None:
    """Raise a one-line `JaxcalError` naming the first parameter of `p` out of its range."""

    def need(ok: bool, msg: str) -> None:
        if not ok:
            raise JaxcalError(f"parameter {msg}")

    pos = ("cell_m", "extent_m", "sigma_r", "sigma_v", "r_est", "window_m")
    for k in pos:
        need(
            math.isfinite(getattr(p, k)) and getattr(p, k) > 0,
            f"{k}: must be a positive number, got {getattr(p, k)!r}",
        )
    need(p.margin_m >= 0, f"margin_m: must be >= 0, got {p.margin_m!r}")
    need(
        math.isfinite(p.window_small_m) and p.window_small_m >= 0,
        f"window_small_m: must be a number >= 0, got {p.window_small_m!r}",
    )
    need(0 < p.tau <= 1, f"tau: must be in (0, 1], got {p.tau!r}")
    need(0 < p.alpha <= 1, f"alpha: must be in (0, 1], got {p.alpha!r}")
    need(0 <= p.p_out < 1, f"p_out: must be in [0, 1), got {p.p_out!r}")
    need(
        p.range_model in RANGE_MODELS,
        f"range_model: one of {', '.join(RANGE_MODELS)}; got {p.range_model!r}",
    )
    need(0 <= p.nlos_weight < 1, f"nlos_weight: must be in [0, 1), got {p.nlos_weight!r}")
    need(
        math.isfinite(p.nlos_mean_m) and p.nlos_mean_m > 0,
        f"nlos_mean_m: must be a positive number, got {p.nlos_mean_m!r}",
    )
    need(p.v >= 0, f"v: must be >= 0, got {p.v!r}")
    for k in ("top_k", "max_hyp", "median_window", "min_refs"):
        need(getattr(p, k) >= 1, f"{k}: must be an integer >= 1, got {getattr(p, k)!r}")
    need(
        p.smoothing in ("none", "ema", "median-ema"),
        f"smoothing: one of none, ema, median-ema; got {p.smoothing!r}",
    )
    need(
        p.likelihood in LIKELIHOODS,
        f"likelihood: one of {', '.join(LIKELIHOODS)}; got {p.likelihood!r}",
    )
    need(p.frame in FRAMES, f"frame: one of {', '.join(FRAMES)}; got {p.frame!r}")
    need(p.grid_mode in GRID_MODES, f"grid_mode: one of {', '.join(GRID_MODES)}; got {p.grid_mode!r}")
    need(p.bias in BIASES, f"bias: one of {', '.join(BIASES)}; got {p.bias!r}")
    for k in ("local_m", "localise_m"):
        need(
            math.isfinite(getattr(p, k)) and getattr(p, k) >= 0,
            f"{k}: must be a number >= 0, got {getattr(p, k)!r}",
        )
    need(
        p.update_order in ("jacobi", "gauss-seidel"),
        f"update_order: jacobi or gauss-seidel; got {p.update_order!r}",
    )
    if p.extent_m / p.cell_m > 2000:
        raise JaxcalError(f"parameter cell_m: grid of {2 * p.extent_m / p.cell_m:.0f} cells a side is too large")


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


def symmetric_ranges(r: np.ndarray) -> np.ndarray:
    """(K, N, N) ranges -> symmetric: mean of i->j and j->i where both exist, else the one there."""
    rt = np.swapaxes(r, 1, 2)
    both = np.isfinite(r) & np.isfinite(rt)
    out = np.where(both, 0.5 * (r + rt), np.where(np.isfinite(r), r, rt))
    n = r.shape[1]
    out[:, np.arange(n), np.arange(n)] = np.nan
    return out


def _remat(cfg: FilterConfig, fn):
    """`fn` under `jax.checkpoint` when the filter is differentiated (`cfg.remat`): a branch of
    `lax.cond` then keeps only its inputs for the backward pass and is recomputed there, instead of
    storing its intermediates (reverse mode of a cond stores the residuals of both branches, the
    branch not taken as zeros). Forward-only runs are unchanged. The time the tuning gradient
    gained came from the per-pair loop bodies (`remat` of `grid.node_loglik_sparse`,
    `fast.ring_loglik_grid`); wrapping these branches alone changed no measured time
    (docs/benchmarks/tuning.md)."""
    return jax.checkpoint(fn) if cfg.remat else fn


_localised = L.localised


def _hypotheses(cfg: FilterConfig, prm: FilterParams, logp: Float[Array, "n c"], cells: Float[Array, "c 2"]):
    """(N, H, 2), (N, H), (N,) hypotheses of all nodes: eq. (10), or eq. (9) for parametric.

    `cells` is (C, 2) shared by all nodes or (N, C, 2) per node (windows)."""
    ca = 0 if cells.ndim == 3 else None
    if cfg.mode == "pgp" and cfg.select == "soft":
        pos, lw = jax.vmap(G.soft_hypotheses, in_axes=(0, ca, None, None, None))(
            logp, cells, cfg.n_hyp, prm.tau, prm.tau_temp
        )
        sig = jnp.broadcast_to(prm.sigma_r, logp.shape[:1])
        return pos, lw, sig
    if cfg.mode == "pgp":
        pos, lw = jax.vmap(G.top_hypotheses, in_axes=(0, ca, None, None))(logp, cells, cfg.n_hyp, prm.tau)
        sig = jnp.broadcast_to(prm.sigma_r, logp.shape[:1])
        return pos, lw, sig
    est = jax.vmap(G.window_estimate, in_axes=(0, ca, None))(logp, cells, prm.r_est)
    _, cov = jax.vmap(G.mean_cov, in_axes=(0, ca))(logp, cells)
    tr = jnp.maximum(jnp.trace(cov, axis1=1, axis2=2), 0.0)
    # eq. (9): the receiver's own uncertainty is its grid, so only the neighbour's trace is added.
    sig = prm.sigma_r + jnp.sqrt(tr)
    return est[:, None, :], jnp.zeros(est.shape[:1] + (1,), est.dtype), sig


def _nlos(cfg: FilterConfig, prm: FilterParams):
    """The `nlos` argument of `grid.pair_loglik` for the configured range model."""
    return (prm.nlos_weight, prm.nlos_mean_m) if cfg.range_model == "mixture" else None


def _node_update(cfg, prm, cells, logp_i, mask_i, loc_i, hyps, z_i, use_i, step_m):
    """One node's epoch: motion update (if localised), eq. (11), eq. (12) posterior (C,)."""
    prior = jax.lax.cond(
        loc_i,
        _remat(cfg, lambda lp: G.predict(lp, cells, cfg.top_k, step_m, prm.sigma_v)),
        lambda lp: lp,
        logp_i,
    )
    if cfg.likelihood == "dense":
        lik = G.node_loglik
    else:
        lik = lambda *a: G.node_loglik_sparse(*a, remat=cfg.remat)  # noqa: E731
    if cfg.window and cfg.mode == "pgp":  # the fast path's full-grid epochs: kernel images
        lik = lambda _cells, *a: F.ring_loglik_grid(cfg.grid, *a, remat=cfg.remat)  # noqa: E731
    ll = lik(cells, hyps[0], hyps[1], hyps[2], z_i, use_i, prm.p_out, _nlos(cfg, prm))
    post = jnp.where(mask_i, prior + ll, -jnp.inf)
    lse = jax.nn.logsumexp(post)
    return post - lse, lse - jax.nn.logsumexp(jnp.where(mask_i, prior, -jnp.inf))


_smooth = L.smooth  # eq. (14)


def _window_epoch(
    cfg: FilterConfig,
    prm: FilterParams,
    inp: FilterInputs,
    st: FilterState,
    z,
    step_m,
    use,
    log_cells,
    w: int,
):
    """One jacobi epoch on W x W windows (`fast.py`): every node localised, posteriors in `st.win`
    (`cfg.window` a side); `w` <= `cfg.window` is the side this epoch runs on (the small window of
    `window_small_m`, or `cfg.window`), its result is placed in a `cfg.window` window (-inf
    outside `w`, covered by the bound).

    a1 runs on its whole row instead (`FilterState.row`). Eq. (11) on the windows is
    `fast.ring_loglik` (one kernel image per pair) when every used neighbour's hypotheses fit its
    block and nothing underflows, else `grid.node_loglik` (same values up to rounding).

    Returns (win, org, bound, ev, raw, row, ok, small_next): `ok` says the new mass outside every
    window is below `fast.WINDOW_LOG_TOL` (else the caller runs the epoch on a bigger window or the
    full grid instead); `small_next` whether the next epoch should try the small window."""
    grid, wb = cfg.grid, cfg.window
    ns = grid.n_side
    n = st.win.shape[0]
    dtype = st.win.dtype
    win = st.win.reshape(n, wb * wb)
    cells_of = jax.vmap(lambda o: F.window_cells(o, grid, wb, dtype))
    wc_old = cells_of(st.org)
    hyps = _hypotheses(cfg, prm, win, wc_old)
    row_cells = jnp.stack([grid.axis(dtype), jnp.zeros((ns,), dtype)], axis=-1)
    h1 = _hypotheses(cfg, prm, st.row[None], row_cells)
    hyps = tuple(h.at[1].set(h1_[0]) for h, h1_ in zip(hyps, h1, strict=True))
    nlos = _nlos(cfg, prm)

    def sources(win_i, org_i, wc_i):
        vals, idx = G.top_k(win_i, cfg.top_k)
        src_idx = org_i[None, :] + jnp.stack([idx // wb, idx % wb], axis=-1)
        flat = src_idx[0, 0] * ns + src_idx[0, 1]
        new_org = F.window_origin(flat, ns, w)
        cells = F.window_cells(new_org, grid, w, dtype)
        prior = F.predict_window(vals, wc_i[idx], cells, step_m, prm.sigma_v)
        return vals, src_idx, F.window_origin(flat, ns, wb), new_org, cells, prior

    vals, src_idx, org_b, org, cells, prior = jax.vmap(sources)(win, st.org, wc_old)

    def direct_ll():
        return jax.vmap(G.node_loglik, in_axes=(0, None, None, None, 0, 0, None, None))(
            cells, hyps[0], hyps[1], hyps[2], z, use, prm.p_out, nlos
        )

    if cfg.mode == "pgp":  # hypotheses are grid cells (eq. 10)
        ll, ring_ok = jax.vmap(F.ring_loglik, in_axes=(0, None, None, None, None, None, 0, 0, None, None))(
            org, w, grid, hyps[0], hyps[1], hyps[2], z, use, prm.p_out, nlos
        )
        ll = jax.lax.cond(jnp.all(ring_ok), lambda: ll, _remat(cfg, direct_ll))
    else:  # eq. (9): off-grid estimates
        ll = direct_ll()

    def node(vals_i, src_i, org_b_i, org_i, cells_i, prior_i, ll_i, mask_i):
        m = F.window_mask(mask_i, org_i, w)
        post = jnp.where(m, prior_i + ll_i, -jnp.inf)
        lse = jax.nn.logsumexp(post)
        ev = lse - jax.nn.logsumexp(jnp.where(m, prior_i, -jnp.inf))
        kw = dict(n_side=ns, cell_m=grid.cell_m, step_m=step_m, sigma_v=prm.sigma_v)
        pb = F.outside_bound(vals_i, src_i, org_i, w=w, **kw)
        post = post - lse
        raw = G.window_estimate(post, cells_i, prm.r_est)
        out = post.reshape(w, w)
        if w < wb:  # the small window lies inside the big one centred on the same cell
            big = jnp.full((wb, wb), -jnp.inf, dtype)
            out = jax.lax.dynamic_update_slice(big, out, tuple(org_i - org_b_i))
            small = pb
        elif cfg.window_small:  # would the small window have held? (lse here >= its lse)
            o_s = F.window_origin(src_i[0, 0] * ns + src_i[0, 1], ns, cfg.window_small)
            small = F.outside_bound(vals_i, src_i, o_s, w=cfg.window_small, **kw)
        else:
            small = jnp.asarray(jnp.inf, dtype)
        return out, pb - lse, ev, raw, small - lse

    win, bound, ev, raw, small = jax.vmap(node)(vals, src_idx, org_b, org, cells, prior, ll, inp.mask)
    # a1 on its row: eq. (7)-(8) from its top_k cells, eq. (11) with a0's hypothesis
    vals, idx = G.top_k(st.row, cfg.top_k)
    d = G.safe_norm(row_cells[None, :, :] - row_cells[idx][:, None, :])
    prior = jax.nn.logsumexp(vals[:, None] - 0.5 * jnp.square((d - step_m) / prm.sigma_v), axis=0)
    ll = G.node_loglik(row_cells, hyps[0], hyps[1], hyps[2], z[1], use[1], prm.p_out, nlos)
    m = inp.mask[1, :, grid.n_half]
    post = jnp.where(m, prior + ll, -jnp.inf)
    lse = jax.nn.logsumexp(post)
    ev = ev.at[1].set(lse - jax.nn.logsumexp(jnp.where(m, prior, -jnp.inf)))
    row = post - lse
    raw = raw.at[1].set(G.window_estimate(row, row_cells, prm.r_est))
    bound = bound.at[1].set(-jnp.inf)
    small = small.at[1].set(-jnp.inf)
    ok = jnp.all(bound + log_cells < F.WINDOW_LOG_TOL)
    # try the small window next only with room to spare: a failed try costs a second epoch
    tol = F.WINDOW_LOG_TOL - F.SMALL_WINDOW_MARGIN
    small_next = bool(cfg.window_small) & jnp.all(small + log_cells < tol)
    return win, org_b, bound, ev, raw, row, ok, small_next


def _windows_epoch(cfg, prm, inp, st: FilterState, z, step_m, use, log_cells):
    """A windowed epoch on the small window (`cfg.window_small`) when the last epoch says it may
    hold, falling back to the big window (`cfg.window`) when its bound fails; the caller falls
    back to the full grid when both fail. Returns `_window_epoch`'s tuple plus whether the small
    window ran."""

    def run(w):
        return _window_epoch(cfg, prm, inp, st, z, step_m, use, log_cells, w)

    def big():
        return run(cfg.window) + (jnp.asarray(False),)

    if not cfg.window_small:
        return big()

    def small_first():
        res = run(cfg.window_small)
        return jax.lax.cond(res[6], lambda: res + (jnp.asarray(True),), big)

    return jax.lax.cond(st.small, small_first, big)


def _full_logpost(cfg: FilterConfig, st: FilterState) -> Float[Array, "n nx ny"]:
    """The state's posteriors on the full grid (windows placed on `-inf` when windowed)."""
    if not cfg.window:
        return st.logpost
    full = jax.vmap(F.scatter_window, in_axes=(0, 0, None))(st.win, st.org, cfg.grid.n_side)
    c = cfg.grid.n_half
    full = full.at[1].set(jnp.full_like(full[1], -jnp.inf).at[:, c].set(st.row))
    return jnp.where(st.windowed, full, st.logpost)


def init_state(cfg: FilterConfig, logpost0: Float[Array, "n nx ny"]) -> FilterState:
    """The filter's state before the first epoch (uniform posteriors over each node's region)."""
    n = logpost0.shape[0]
    w = cfg.window or 1
    dtype = logpost0.dtype
    nan2 = jnp.full((n, 2), jnp.nan, dtype)
    return FilterState(
        logpost=logpost0,
        heard=jnp.zeros((n, n), bool),
        smooth=nan2,
        started=jnp.zeros((n,), bool),
        buf=jnp.full((n, cfg.median_window, 2), jnp.nan, dtype),
        snaps=jnp.full((cfg.n_snap,) + logpost0.shape, -jnp.inf, dtype),
        win=jnp.zeros((n, w, w), dtype),
        org=jnp.zeros((n, 2), jnp.int32),
        bound=jnp.full((n,), jnp.inf, dtype),
        windowed=jnp.asarray(False),
        row=jnp.full((cfg.grid.n_side,), -jnp.inf, dtype),
        small=jnp.asarray(True),
    )


def _scan(cfg: FilterConfig, prm: FilterParams, inp: FilterInputs, st0: FilterState, k0=0):
    """`lax.scan` of the epochs `inp.z` from state `st0` (`k0`: index of the first epoch, for
    snapshots) -> (FilterState, FilterOut). The state may be windowed (see `_full_logpost`)."""
    n = st0.logpost.shape[0]
    dtype = st0.logpost.dtype
    cells = cfg.grid.cells(dtype)
    c = cells.shape[0]
    mask = inp.mask.reshape(n, c)
    nan2 = jnp.full((n, 2), jnp.nan, dtype)
    windowed_mode = cfg.window > 0 and cfg.update_order == "jacobi"
    # log of each node's number of allowed cells: bounds the mass outside its window
    log_cells = jnp.log(jnp.maximum(jnp.sum(mask, axis=1), 1).astype(dtype))

    def upd(lp, loc, hyps, z, use, step_m):
        args = (lp, mask, loc, z, use)
        if cfg.likelihood != "dense":  # lax.map: a vmapped cond would evaluate the skipped work too
            return jax.lax.map(
                lambda a: _node_update(cfg, prm, cells, a[0], a[1], a[2], hyps, a[3], a[4], step_m),
                args,
            )
        return jax.vmap(lambda *a: _node_update(cfg, prm, cells, a[0], a[1], a[2], hyps, a[3], a[4], step_m))(*args)

    def full_epoch(st: FilterState, z, step_m):
        """The direct evaluation on every cell; re-centres the windows when there are any."""
        lp = _full_logpost(cfg, st).reshape(n, c)
        heard = st.heard
        if cfg.update_order == "jacobi":
            loc = _localised(heard, inp.need)
            use = inp.allowed & jnp.isfinite(z) & loc[None, :]
            hyps = _hypotheses(cfg, prm, lp, cells)
            lp, ev = upd(lp, loc, hyps, z, use, step_m)
            heard = heard | use
            nf = jnp.sum(use, axis=1).astype(dtype)
        else:
            hyps = _hypotheses(cfg, prm, lp, cells)

            def one(carry, i):
                lp, heard, hyps = carry
                loc = _localised(heard, inp.need)
                use_i = inp.allowed[i] & jnp.isfinite(z[i]) & loc
                new, ev_i = _node_update(cfg, prm, cells, lp[i], mask[i], loc[i], hyps, z[i], use_i, step_m)
                lp = lp.at[i].set(new)
                heard = heard.at[i].set(heard[i] | use_i)
                h1 = _hypotheses(cfg, prm, new[None], cells)
                hyps = tuple(h.at[i].set(h1_[0]) for h, h1_ in zip(hyps, h1, strict=True))
                return (lp, heard, hyps), (ev_i, jnp.sum(use_i).astype(dtype))

            (lp, heard, _), (ev, nf) = jax.lax.scan(one, (lp, heard, hyps), jnp.arange(n))
        raw = jax.vmap(G.window_estimate, in_axes=(0, None, None))(lp, cells, prm.r_est)
        logpost = lp.reshape(st.logpost.shape)
        if windowed_mode:
            win, org, bound = jax.vmap(F.extract_window, in_axes=(0, None))(logpost, cfg.window)
            row = logpost[1, :, cfg.grid.n_half]
            bound = bound.at[1].set(-jnp.inf)  # a1 is kept as its whole row
        else:
            win, org, bound, row = st.win, st.org, st.bound, st.row
        lm = jax.nn.logsumexp(lp, axis=1)
        return logpost, heard, ev, nf, raw, win, org, bound, row, lm

    def epoch(st: FilterState, x):
        z, dt, k = x
        step_m = prm.v * dt
        if windowed_mode:
            loc0 = _localised(st.heard, inp.need)
            use0 = inp.allowed & jnp.isfinite(z) & loc0[None, :]
            pre = jnp.all(loc0) & jnp.all(st.bound + log_cells < F.WINDOW_LOG_TOL)
            skip = (
                st.win,
                st.org,
                st.bound,
                jnp.zeros((n,), dtype),
                nan2,
                st.row,
                jnp.asarray(False),
                jnp.asarray(True),
                jnp.asarray(False),
            )
            res = jax.lax.cond(
                pre,
                _remat(cfg, lambda: _windows_epoch(cfg, prm, inp, st, z, step_m, use0, log_cells)),
                lambda: skip,
            )
            ok = pre & res[6]
            # after a full-grid epoch the windows are re-centred: try the small one first again
            small_next = jnp.where(ok, res[7], True)
            ran_small = ok & res[8]

            # the full grid is an explicit operand (not a closure constant) of both branches, so
            # the windowed branch can hand it through without a copy
            def take_window(lp_full):
                nf = jnp.sum(use0, axis=1).astype(dtype)
                lm = jax.nn.logsumexp(res[0].reshape(n, -1), axis=1)
                lm = lm.at[1].set(jax.nn.logsumexp(res[5]))
                return (
                    lp_full,
                    st.heard | use0,
                    res[3],
                    nf,
                    res[4],
                    res[0],
                    res[1],
                    res[2],
                    res[5],
                    lm,
                )

            def take_full(lp_full):
                return full_epoch(dataclasses.replace(st, logpost=lp_full), z, step_m)

            logpost, heard, ev, nf, raw, win, org, bound, row, lm = jax.lax.cond(
                ok, take_window, _remat(cfg, take_full), st.logpost
            )
            windowed = ok
        else:
            logpost, heard, ev, nf, raw, win, org, bound, row, lm = full_epoch(st, z, step_m)
            windowed = st.windowed
            small_next, ran_small = st.small, jnp.asarray(False)
        loc = _localised(heard, inp.need)
        raw = jnp.where(loc[:, None], raw, nan2)
        est, smooth, started, buf = _smooth(cfg, prm, st, raw, loc)
        est = jnp.where(loc[:, None], est, nan2)
        new = FilterState(
            logpost,
            heard,
            smooth,
            started,
            buf,
            st.snaps,
            win,
            org,
            bound,
            windowed,
            row,
            small_next,
        )
        if cfg.n_snap:
            hit = inp.snap_at == k
            snaps = jax.lax.cond(
                jnp.any(hit),
                lambda: jnp.where(hit[:, None, None, None], _full_logpost(cfg, new)[None], st.snaps),
                lambda: st.snaps,
            )
            new = dataclasses.replace(new, snaps=snaps)
        return new, FilterOut(est, raw, lm, ev, nf, windowed, ran_small)

    k = inp.z.shape[0]
    body = jax.checkpoint(epoch) if cfg.remat else epoch
    return jax.lax.scan(body, st0, (inp.z, inp.dt, k0 + jnp.arange(k)))


def _filter(cfg: FilterConfig, prm: FilterParams, inp: FilterInputs, logpost0: Float[Array, "n nx ny"]):
    """The recursive filter: `lax.scan` over epochs -> (final FilterState, per-epoch FilterOut).

    The final state's `logpost` holds the full-grid posteriors (windows placed on the grid)."""
    st, out = _scan(cfg, prm, inp, init_state(cfg, logpost0))
    return full_state(cfg, st), out


run_filter = eqx.filter_jit(_filter)
"""The recursive filter, jitted (`eqx.filter_jit`): (cfg, prm, inp, logpost0) -> (final FilterState,
per-epoch FilterOut); tuning and sweeps call it (also inside their own vmap / jit)."""
_scan_jit = eqx.filter_jit(_scan)


def _scan_windows(cfg: FilterConfig, prm: FilterParams, inp: FilterInputs, st: FilterState, valid, k0):
    """Windowed epochs only, without the full grid in the carry (its copies cost O(cells) per
    epoch). Stops (state frozen) at the first epoch that is not `valid` or cannot run on the
    windows; returns (state, FilterOut, epochs done). `st.logpost` is not read."""
    n = st.win.shape[0]
    dtype = st.win.dtype
    mask = inp.mask.reshape(n, -1)
    log_cells = jnp.log(jnp.maximum(jnp.sum(mask, axis=1), 1).astype(dtype))
    nan2 = jnp.full((n, 2), jnp.nan, dtype)

    def epoch(carry, x):
        st, go = carry
        z, dt, k, v = x
        step_m = prm.v * dt
        loc0 = _localised(st.heard, inp.need)
        use0 = inp.allowed & jnp.isfinite(z) & loc0[None, :]
        pre = jnp.all(loc0) & jnp.all(st.bound + log_cells < F.WINDOW_LOG_TOL)
        no = jnp.asarray(False)
        skip = (st.win, st.org, st.bound, jnp.zeros((n,), dtype), nan2, st.row, no, st.small, no)
        win, org, bound, ev, raw, row, ok, small_next, ran_small = jax.lax.cond(
            go & v & pre,
            lambda: _windows_epoch(cfg, prm, inp, st, z, step_m, use0, log_cells),
            lambda: skip,
        )
        go = go & v & pre & ok
        heard = st.heard | use0
        loc = _localised(heard, inp.need)
        raw = jnp.where(loc[:, None], raw, nan2)
        est, smooth, started, buf = _smooth(cfg, prm, st, raw, loc)
        est = jnp.where(loc[:, None], est, nan2)
        lm = jax.nn.logsumexp(win.reshape(n, -1), axis=1).at[1].set(jax.nn.logsumexp(row))
        new = dataclasses.replace(
            st,
            heard=heard,
            smooth=smooth,
            started=started,
            buf=buf,
            win=win,
            org=org,
            bound=bound,
            row=row,
            windowed=jnp.asarray(True),
            small=small_next,
        )
        new = jax.tree.map(lambda a, b: jnp.where(go, a, b), new, st)
        nf = jnp.sum(use0, axis=1).astype(dtype)
        return (new, go), (FilterOut(est, raw, lm, ev, nf, go, go & ran_small), go)

    k = inp.z.shape[0]
    (st, _), (out, done) = jax.lax.scan(epoch, (st, jnp.asarray(True)), (inp.z, inp.dt, k0 + jnp.arange(k), valid))
    return st, out, jnp.sum(done)


_scan_windows_jit = eqx.filter_jit(_scan_windows)


def run_chunked(
    cfg: FilterConfig,
    prm: FilterParams,
    inp: FilterInputs,
    logpost0,
    chunk: int = 64,
    full_chunk: int = 4,
    progress=None,
):
    """`run_filter` for `likelihood="window"` driven from the host in chunks of epochs.

    Same epochs, same results as `run_filter`; while the windows hold, chunks of `chunk` epochs
    run without the full grid in the scan's carry (`_scan_windows`); other epochs run in chunks of
    `full_chunk` with the full grid (`_scan`). Each chunk length compiles once.

    Args:
        progress: optional callback, called with the number of epochs done since its last call
            (after every chunk). Without the fast path (other likelihoods, snapshots) the one
            scan then runs in segments (`run_segmented`); results are identical either way.

    Returns:
        (final FilterState with the full-grid `logpost`, FilterOut of all epochs).
    """
    if not cfg.window or cfg.n_snap:
        if progress is not None:
            return run_segmented(cfg, prm, inp, logpost0, progress=progress)
        return run_filter(cfg, prm, inp, logpost0)
    st, out = advance_chunked(cfg, prm, inp, init_state(cfg, logpost0), 0, None, chunk, full_chunk, progress)
    return full_state(cfg, st), out


def full_state(cfg: FilterConfig, st: FilterState) -> FilterState:
    """The state with its full-grid `logpost` (windows placed on the grid), not windowed."""
    return dataclasses.replace(st, logpost=_full_logpost(cfg, st), windowed=jnp.asarray(False))


def advance_chunked(
    cfg: FilterConfig,
    prm: FilterParams,
    inp: FilterInputs,
    st: FilterState,
    start: int = 0,
    stop: int | None = None,
    chunk: int = 64,
    full_chunk: int = 4,
    progress=None,
) -> tuple[FilterState, FilterOut]:
    """Epochs `start:stop` of `inp` from state `st` on `run_chunked`'s fast path (which is this
    from `init_state` over all epochs, then `full_state`).

    The returned state is the scan's own (possibly windowed: `logpost` stale), so a later call
    with `start=stop` continues exactly where this one ended: two calls give the epochs and the
    state of one (tested). Needs `cfg.window` and no snapshots.

    Returns:
        (state after epoch `stop - 1`, FilterOut of epochs `start:stop`).
    """
    if not cfg.window or cfg.n_snap:
        raise ValueError("advance_chunked: needs the windowed likelihood and no snapshots")
    n_ep = int(inp.z.shape[0]) if stop is None else int(stop)
    n = st.logpost.shape[0]
    log_cells = np.log(np.maximum(np.asarray(inp.mask).reshape(n, -1).sum(1), 1))
    outs, k = [], int(start)

    def part(a, b, pad=0):
        z, dt = inp.z[a:b], inp.dt[a:b]
        if pad:
            z = jnp.concatenate([z, jnp.full((pad,) + z.shape[1:], jnp.nan, z.dtype)])
            dt = jnp.concatenate([dt, jnp.zeros((pad,), dt.dtype)])
        return dataclasses.replace(inp, z=z, dt=dt)

    while k < n_ep:
        loc = np.asarray(_localised(st.heard, inp.need))
        if loc.all() and np.all(np.asarray(st.bound) + log_cells < F.WINDOW_LOG_TOL):
            m = min(chunk, n_ep - k)
            valid = jnp.arange(chunk) < m
            full = st.logpost
            small = dataclasses.replace(st, logpost=jnp.zeros((n, 1, 1), full.dtype))
            st2, out, done = _scan_windows_jit(cfg, prm, part(k, k + m, chunk - m), small, valid, jnp.asarray(k))
            done = int(done)
            if done:
                st = dataclasses.replace(st2, logpost=full)
                outs.append(jax.tree.map(lambda a, d=done: a[:d], out))
                k += done
                if progress is not None:
                    progress(done)
            if done == m:
                continue
        m = full_chunk if n_ep - k >= full_chunk else 1
        st, out = _scan_jit(cfg, prm, part(k, k + m), st, jnp.asarray(k))
        outs.append(out)
        k += m
        if progress is not None:
            progress(m)
    if not outs:
        raise ValueError(f"advance_chunked: no epochs in {start}:{n_ep}")
    return st, jax.tree.map(lambda *a: jnp.concatenate(a), *outs)


def run_segmented(
    cfg: FilterConfig,
    prm: FilterParams,
    inp: FilterInputs,
    logpost0,
    segment: int = 64,
    progress=None,
):
    """`run_filter` as a host loop over segments of `segment` epochs (one jitted `_scan` per
    segment, the state carried from one call to the next), calling `progress(epochs)` after each.

    The same scan body on the same state: results are bit-for-bit those of `run_filter`
    (tested). Segments of one length compile once (plus once for a shorter last segment).

    Returns:
        (final FilterState with the full-grid `logpost`, FilterOut of all epochs).
    """
    n_ep = int(inp.z.shape[0])
    st = init_state(cfg, logpost0)
    outs = []
    for k in range(0, n_ep, segment):
        m = min(segment, n_ep - k)
        part = dataclasses.replace(inp, z=inp.z[k : k + m], dt=inp.dt[k : k + m])
        st, out = _scan_jit(cfg, prm, part, st, jnp.asarray(k))
        outs.append(out)
        if progress is not None:
            progress(m)
    out = jax.tree.map(lambda *a: jnp.concatenate(a), *outs)
    return full_state(cfg, st), out


def _neighbour_sets(params: PGPParams, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(allowed (N, N), need (N,)) in filter order: structural neighbours (eq. 5, 6, 11) and the
    localised neighbours each node must hear before it is localised."""
    allowed = np.ones((n, n), dtype=bool)
    np.fill_diagonal(allowed, False)
    allowed[0] = False
    allowed[1] = False
    allowed[1, 0] = True
    if not params.a2_all:
        allowed[2] = False
        allowed[2, :2] = True
    need = np.full(n, float(params.min_refs))
    need[:3] = (0.0, 1.0, 2.0)
    return allowed, need


def _setup(params: PGPParams, grid: G.Grid, n: int, mode: str, snaps: np.ndarray, z, dt):
    """(cfg, prm, inp, logpost0) for `n` nodes in filter order on `grid` (host side)."""
    mask = G.region_masks(grid, n)
    allowed, need = _neighbour_sets(params, n)
    ftype = jnp.result_type(float)
    window = window_small = 0
    if params.likelihood == "window" and params.update_order == "jacobi":
        window = F.window_side(params.window_m, grid)
        if window * window < params.top_k or grid.n_side < params.top_k:
            window = 0  # the windows (and a1's row) must hold the top_k cells of eq. (7)
        small = F.window_side(params.window_small_m, grid) if params.window_small_m > 0 else 0
        if window and small * small >= params.top_k and small < window:
            window_small = small
    cfg = FilterConfig(
        grid=grid,
        top_k=min(params.top_k, grid.n_cells),
        n_hyp=min(params.max_hyp, grid.n_cells),
        update_order=params.update_order,
        smoothing=params.smoothing,
        median_window=params.median_window,
        mode=mode,
        n_snap=int(snaps.size),
        likelihood="direct" if params.likelihood in ("window", "sparse") else params.likelihood,
        window=window,
        window_small=window_small,
        range_model=params.range_model,
    )
    prm = FilterParams(*(jnp.asarray(getattr(params, f), ftype) for f in NUMERIC))
    inp = FilterInputs(
        z=jnp.asarray(z, ftype),
        dt=jnp.asarray(dt, ftype),
        mask=jnp.asarray(mask),
        allowed=jnp.asarray(allowed),
        need=jnp.asarray(need, ftype),
        snap_at=jnp.asarray(snaps, ftype),
    )
    logpost0 = jnp.where(inp.mask, 0.0, -jnp.inf).astype(ftype)
    logpost0 = logpost0 - jax.nn.logsumexp(logpost0, axis=(1, 2), keepdims=True)
    return cfg, prm, inp, logpost0


def _node_order(n: int, anchors) -> np.ndarray:
    a0, a1, a2 = (int(a) for a in anchors)
    if len({a0, a1, a2}) != 3 or min(a0, a1, a2) < 0 or max(a0, a1, a2) >= n:
        raise JaxcalError(f"anchors must be three distinct node indices in [0, {n}), got {anchors}")
    return np.array([a0, a1, a2] + [i for i in range(n) if i not in (a0, a1, a2)])


def prepare(
    dataset: MeshDataset,
    params: PGPParams,
    config: str | None,
    mode: str = "pgp",
    snapshot_epochs=(),
    anchors=None,
):
    """Host-side setup: node order, grid, masks and arrays for `_filter`.

    `anchors` (a0, a1, a2) overrides the configuration's frame (the proxy frame of `run_pgp`).

    Returns:
        (cfg, prm, inp, logpost0, order) where `order[k]` is the dataset index of filter node k.
    """
    validate_params(params)
    n = dataset.n_nodes
    order = _node_order(n, dataset.config(config) if anchors is None else anchors)
    z = symmetric_ranges(np.asarray(dataset.range, dtype=np.float64))[:, order][:, :, order]
    radius = G.extent_radius(z, 0, params.margin_m, params.extent_m)
    grid = G.make_grid(radius, params.cell_m)
    t = np.asarray(dataset.time, dtype=np.float64)
    dt = np.diff(t, prepend=t[:1]) if t.size else t
    snaps = np.asarray(sorted({int(s) for s in snapshot_epochs}), dtype=np.float64)
    if snaps.size and (snaps.min() < 0 or snaps.max() >= max(dataset.n_epochs, 1)):
        raise JaxcalError(f"snapshot epochs must lie in [0, {dataset.n_epochs})")
    cfg, prm, inp, logpost0 = _setup(params, grid, n, mode, snaps, z, dt)
    return cfg, prm, inp, logpost0, order


class PGPStream(eqx.Module):
    """A running filter fed chunk by chunk (`start`, `advance`): live calibration.

    Attributes:
        cfg, prm: static configuration and numeric parameters. inp: constant inputs (masks,
            neighbour sets; its `z`, `dt` are unused). state: the filter state after `epochs`
            epochs. order: `order[k]` is the dataset index of filter node k. epochs: epochs done.
    """

    cfg: FilterConfig
    prm: FilterParams
    inp: FilterInputs
    state: FilterState
    order: tuple[int, ...] = eqx.field(static=True)
    epochs: int = eqx.field(static=True, default=0)


def start(
    n_nodes: int,
    params: PGPParams | dict | None = None,
    anchors=(0, 1, 2),
    radius_m: float | None = None,
    *,
    mode: str = "pgp",
) -> PGPStream:
    """Start a filter for live use: no epochs yet.

    Args:
        n_nodes: N, the number of nodes (dataset order; ranges fed later are (k, N, N)).
        params: a `PGPParams` or dict of overrides. anchors: (a0, a1, a2) node indices.
        radius_m: half-width of the grid [m] (None: `params.extent_m`; `run_pgp` sizes it from the
            ranges with `grid.extent_radius`, which needs the recording first).
        mode: "pgp" or "parametric".

    Returns:
        a `PGPStream` to pass to `advance`.
    """
    if not isinstance(params, PGPParams):
        params = with_overrides(PGPParams(), params)
    validate_params(params)
    order = _node_order(int(n_nodes), anchors)
    radius = params.extent_m if radius_m is None else float(radius_m)
    if not (math.isfinite(radius) and radius > 0):
        raise JaxcalError(f"radius_m must be a positive number, got {radius_m!r}")
    grid = G.make_grid(radius, params.cell_m)
    n = int(n_nodes)
    cfg, prm, inp, lp0 = _setup(params, grid, n, mode, np.zeros(0), np.zeros((0, n, n)), np.zeros(0))
    return PGPStream(cfg, prm, inp, init_state(cfg, lp0), tuple(int(i) for i in order), 0)


def advance(stream: PGPStream, ranges: np.ndarray, dt: np.ndarray) -> tuple[PGPStream, np.ndarray]:
    """Feed the next epochs to a running filter.

    Advancing in chunks gives the same estimates as one run over all epochs (each chunk length
    compiles once: feed chunks of a fixed size for live use).

    Args:
        stream: from `start` or a previous `advance`.
        ranges: (k, N, N) ranges [m] of the next k epochs, dataset node order, NaN missing.
        dt: (k,) time step of each epoch to the one before [s] (0 for the very first).

    Returns:
        (stream, estimates): the advanced stream and (k, N, 2) eq. (13)/(14) estimates [m] in the
        configuration frame, dataset node order, NaN while a node is not localised.
    """
    r = np.asarray(ranges, dtype=np.float64)
    d = np.asarray(dt, dtype=np.float64)
    n = len(stream.order)
    if r.ndim != 3 or r.shape[1:] != (n, n) or d.shape != r.shape[:1]:
        raise JaxcalError(f"advance: need ranges (k, {n}, {n}) and dt (k,), got {r.shape}, {d.shape}")
    order = np.asarray(stream.order)
    z = symmetric_ranges(r)[:, order][:, :, order]
    dtype = stream.state.logpost.dtype
    inp = dataclasses.replace(stream.inp, z=jnp.asarray(z, dtype), dt=jnp.asarray(d, dtype))
    k0 = jnp.asarray(stream.epochs, jnp.int32)  # an array: no recompilation per chunk
    st, out = _scan_jit(stream.cfg, stream.prm, inp, stream.state, k0)
    est = np.asarray(out.estimate, dtype=np.float64)[:, np.argsort(order)]
    new = PGPStream(stream.cfg, stream.prm, stream.inp, st, stream.order, stream.epochs + r.shape[0])
    return new, est


def stream_posterior(stream: PGPStream) -> np.ndarray:
    """(N, n, n) current posterior probabilities on the stream's grid, dataset node order."""
    lp = np.asarray(_full_logpost(stream.cfg, stream.state), dtype=np.float64)
    return np.exp(lp)[np.argsort(np.asarray(stream.order))]


def cell_variance(cell_m: float, n: int, anchors: tuple[int, int, int]) -> np.ndarray:
    """(n, 2, 2) within-cell variance cell^2 / 12 per free axis (a0: none; a1: x only).

    The grid posterior puts each cell's probability on its centre; read as a histogram density
    (uniform within each cell), its covariance is the centres' covariance plus cell^2 / 12 on each
    axis the node is free in. Without it a node whose posterior sits in one cell reports a variance
    near 0 although it is only known to within a cell, and its NEES is far above 1 (the NEES with
    and without this term: the benchmarks page of the docs).
    """
    out = np.zeros((n, 2, 2))
    q = cell_m * cell_m / 12.0
    out[:, 0, 0] = out[:, 1, 1] = q
    out[anchors[0]] = 0.0
    out[anchors[1], 1, 1] = 0.0
    return out


def run_pgp(
    dataset: MeshDataset,
    params: PGPParams | dict | None = None,
    config: str | None = None,
    *,
    mode: str = "pgp",
    snapshot_epochs=(),
    progress=None,
    posterior: bool = True,
) -> tuple[Result, PGPInfo]:
    """Run the grid filter on a mesh dataset.

    Args:
        dataset: the mesh recording (K epochs, N nodes).
        params: a `PGPParams` or a dict of overrides of its defaults (strings are cast).
        config: the frame configuration's name (None: `default` or (0, 1, 2)).
        mode: "pgp" (eq. 10-11) or "parametric" (eq. 9).
        snapshot_epochs: epochs whose posterior grids are returned in `PGPInfo.snapshots`.
        progress: optional callback, called with the epochs done since its last call (the scan
            runs in chunks; results do not depend on it).
        posterior: fill `PGPInfo.posterior` (with node-local grids, `grid_mode`, that is an
            (N, n, n) array on the whole lattice, built for inspection; False: an empty array).

    Returns:
        (Result, PGPInfo): positions, covariance and per-epoch track in the configuration frame,
        and the
        posterior grids in the dataset's node order.
    """
    if not isinstance(params, PGPParams):
        params = with_overrides(PGPParams(), params)
    if dataset.n_epochs == 0:
        raise JaxcalError(f"{dataset.name}: no epochs to calibrate from")
    a = dataset.config(config)
    b = a if params.frame == "direct" else _filter_anchors(dataset, a, params.frame)
    validate_params(params)
    local = None
    if params.grid_mode != "global":
        local = _local_setup(dataset, params, b, mode, bool(len(snapshot_epochs)))
    if params.bias == "network" or (params.bias == "auto" and local is not None):
        return _run_offset(dataset, params, config, mode, snapshot_epochs, progress, posterior, (a, b, local))
    if local is not None:
        return _run_local(dataset, params, a, b, local, progress, posterior)
    cfg, prm, inp, logpost0, order = prepare(dataset, params, config, mode, snapshot_epochs, b)
    st, out = run_chunked(cfg, prm, inp, logpost0, progress=progress)
    cells = cfg.grid.cells(logpost0.dtype)
    n = logpost0.shape[0]
    lp = st.logpost.reshape(n, -1)
    _, cov = jax.vmap(G.mean_cov, in_axes=(0, None))(lp, cells)
    inv = np.argsort(order)
    est = np.asarray(out.estimate, dtype=np.float64)[:, inv]
    raw = np.asarray(out.raw, dtype=np.float64)[:, inv]
    loc_any = np.isfinite(est).all(axis=2).any(axis=0)
    final = est[-1]
    cov = np.asarray(cov, dtype=np.float64)[inv]
    cov = cov + cell_variance(cfg.grid.cell_m, n, b)
    cov[~loc_any] = np.nan
    if b != a:  # proxy frame: every epoch moved into the configuration's frame by its a0, a1, a2
        final, cov, est = _to_config_frame(final, cov, est, a)
        loc_any = np.isfinite(est).all(axis=2).any(axis=0)
    res = _result(dataset, params, mode, a, final, cov, est)
    info = PGPInfo(
        axis_m=np.asarray(cfg.grid.axis(np.float64)),
        posterior=np.exp(np.asarray(st.logpost, dtype=np.float64))[inv],
        snapshot_epochs=np.asarray(inp.snap_at, dtype=np.int64),
        snapshots=np.exp(np.asarray(st.snaps, dtype=np.float64))[:, inv],
        log_mass=np.asarray(out.log_mass, dtype=np.float64)[:, inv],
        raw_track=raw,
        localised=loc_any,
        frame=f"anchors:{b[0]},{b[1]},{b[2]}",
    )
    return res, info


def uses_local(dataset: MeshDataset, params=None, config: str | None = None, mode: str = "pgp") -> bool:
    """Whether `run_pgp` (and so `calibrate`) runs `dataset` on node-local grids (`grid_mode`, `local.py`):
    tools that drive the global-grid filter themselves (tune, live, sweeps) check it."""
    if not isinstance(params, PGPParams):
        params = with_overrides(PGPParams(), params)
    if params.grid_mode == "global" or dataset.n_epochs == 0:
        return False
    a = dataset.config(config)
    b = a if params.frame == "direct" else _filter_anchors(dataset, a, params.frame)
    return _local_setup(dataset, params, b, mode, False) is not None


def global_grid_only(tool: str, site: str) -> JaxcalError:
    """The one-line refusal of a tool that runs the global grid only (`tool`: "tune", "live
    calibration") on a site where `calibrate` runs node-local grids (`uses_local`)."""
    return JaxcalError(
        f"{site}: the site is wider than one node-local grid, where calibrate --method pgp runs node-local "
        f"grids (grid_mode=auto), which {tool} does not run; use --set grid_mode=global here and for "
        "calibrate to run the global grid in both"
    )


def _run_offset(
    dataset: MeshDataset, params: PGPParams, config, mode, snapshot_epochs, progress, posterior: bool, where
):
    """`run_pgp` with `bias` "network" (or "auto" on node-local grids): a first run on the first
    `OFFSET_EPOCHS` epochs, the offset fitted to its positions (`range_offset.fit_offset`), then the run
    on every range minus the offset. The result's `params` are `params` (a rerun fits the same offset).
    `where`: (a, b, `_local_setup` or None). On node-local grids both runs take the lattice, wide side
    and neighbour lists of the recording's own ranges (one compilation for both)."""
    import logging

    from jaxcal.mesh.range_offset import fit_offset, pair_medians

    log = logging.getLogger("jaxcal")
    plain = dataclasses.replace(params, bias="none")
    r = np.asarray(dataset.range)
    k = min(OFFSET_EPOCHS, dataset.n_epochs)
    short = dataclasses.replace(dataset, time=np.asarray(dataset.time)[:k], range=r[:k], fp_rssi=None, rx_rssi=None)
    a, b, local = where

    def run(ds, z_run, prog, post, snaps=()):
        if local is None:
            return run_pgp(ds, plain, config, mode=mode, snapshot_epochs=snaps, progress=prog, posterior=post)
        order, z, dt, lattice, wide = local
        return _run_local(ds, plain, a, b, (order, z_run, dt[: z_run.shape[0]], lattice, wide), prog, post, setup_z=z)

    level = log.level
    log.setLevel(logging.ERROR)  # the first run's warnings (unplaced nodes...) are the second run's to give
    try:
        first, _ = run(short, None if local is None else local[1][:k], None, False)
    finally:
        log.setLevel(level)
    z_run = None if local is None else local[1]
    c, pairs = fit_offset(np.asarray(first.position), pair_medians(symmetric_ranges(r)), params.sigma_r)
    if np.isfinite(c):
        log.info(
            "pgp: range offset %+.3f m fitted from %d pairs (bias=%s), subtracted from every range",
            c,
            pairs,
            params.bias,
        )
        shifted = np.where(np.isfinite(r), np.maximum(r - c, 0.0), r)
        dataset = dataclasses.replace(dataset, range=shifted)
        z_run = None if z_run is None else np.where(np.isfinite(z_run), np.maximum(z_run - c, 0.0), z_run)
    else:
        log.warning("pgp: range offset not fitted (too few pairs between placed nodes): ranges taken as unbiased")
    res, info = run(dataset, z_run, progress, posterior, snapshot_epochs)
    res = dataclasses.replace(res, params=as_dict(params))
    return res, dataclasses.replace(info, offset_m=c if np.isfinite(c) else float("nan"))


def _result(dataset: MeshDataset, params: PGPParams, method: str, a, final, cov, est) -> Result:
    """The `Result` of a filter run: final positions and covariances, the track, in the frame a0, a1, a2 = `a`."""
    return Result(
        ids=dataset.node_ids,
        position=final,
        method=method,
        dataset=dataset.name,
        frame=f"anchors:{a[0]},{a[1]},{a[2]}",
        params=as_dict(params),
        covariance=cov,
        track_time=np.asarray(dataset.time, dtype=np.float64),
        track_position=est,
        software=_software(),
    )


def local_site(params: PGPParams, z: np.ndarray, anchors, mode: str = "pgp", snapshots: bool = False) -> bool:
    """Whether `run_pgp` takes node-local grids for (K, N, N) symmetric ranges `z` (`symmetric_ranges`)
    in the frame of `anchors`: `grid_mode`, and the global grid wider than one node-local grid."""
    if params.grid_mode == "global":
        return False
    wide = L.wide_side(z, params.margin_m, params.cell_m, params.local_m)
    full = G.make_grid(G.extent_radius(z, anchors[0], params.margin_m, params.extent_m), params.cell_m)
    return L.use_local(params, full.n_side, wide, mode, snapshots)


def _local_setup(dataset: MeshDataset, params: PGPParams, anchors, mode: str, snapshots: bool):
    """(order, z, dt, lattice, wide side) when `run_pgp` takes the node-local grids (`local.py`),
    else None."""
    n = dataset.n_nodes
    order = _node_order(n, anchors)
    z = symmetric_ranges(np.asarray(dataset.range, dtype=np.float64))[:, order][:, :, order]
    if not local_site(params, z, (0, 1, 2), mode, snapshots):
        return None
    wide = L.wide_side(z, params.margin_m, params.cell_m, params.local_m)
    radius = G.extent_radius(z, 0, params.margin_m, math.inf)
    radius = (wide // 2 + 1) * params.cell_m if not math.isfinite(radius) else radius
    lattice = G.make_grid(max(radius, (wide // 2 + 1) * params.cell_m), params.cell_m)
    t = np.asarray(dataset.time, dtype=np.float64)
    dt = np.diff(t, prepend=t[:1]) if t.size else t
    return order, z, dt, lattice, wide


def _run_local(dataset: MeshDataset, params: PGPParams, a, b, local, progress, posterior: bool, setup_z=None):
    """`run_pgp` on node-local grids (`local.py`): the same `Result` and `PGPInfo` (the lattice's axis,
    the posteriors placed on it when `posterior`; no snapshots). `setup_z`: the ranges that size the
    neighbour lists (default: `local`'s)."""
    order, z, dt, lattice, wide = local
    n = dataset.n_nodes
    allowed, need = _neighbour_sets(params, n)
    cfg, kind, log_cells, nbrs = L.setup(params, n, z if setup_z is None else setup_z, allowed, lattice, wide)
    ftype = jnp.result_type(float)
    prm = FilterParams(*(jnp.asarray(getattr(params, f), ftype) for f in NUMERIC))
    st, out, cov = L.run_local(
        cfg, prm, jnp.asarray(allowed), jnp.asarray(need, ftype), kind, log_cells, nbrs, z, dt, progress=progress
    )
    inv = np.argsort(order)
    est = np.asarray(out.estimate, dtype=np.float64)[:, inv]
    raw = np.asarray(out.raw, dtype=np.float64)[:, inv]
    loc_any = np.isfinite(est).all(axis=2).any(axis=0)
    final = est[-1]
    cov = np.asarray(cov, dtype=np.float64)[inv] + cell_variance(lattice.cell_m, n, b)
    cov[~loc_any] = np.nan
    if b != a:
        final, cov, est = _to_config_frame(final, cov, est, a)
        loc_any = np.isfinite(est).all(axis=2).any(axis=0)
    import logging

    log = logging.getLogger("jaxcal")
    lost = int(np.asarray(out.lost).sum())
    if lost:  # a just-localised node whose top_k cells still include a far mode of tiny mass
        # the proven bound on the dropped mass; above 1 it bounds nothing (the mass itself is at most 1)
        frac = min(float(np.exp(np.nanmax(np.asarray(out.lost_log)))), 1.0)
        (log.warning if frac > 1e-3 else log.debug)(
            "pgp: in %d node-epochs up to %.1e (a bound) of a node's probability lay outside its %.0f m grid "
            "and was dropped",
            lost,
            frac,
            wide * lattice.cell_m,
        )
    never = [dataset.node_ids[i] for i in np.flatnonzero(~loc_any)]
    if never:
        log.warning(
            "pgp: %d node(s) never localised, left unplaced (NaN): %s (fewer than min_refs localised "
            "neighbours, or a posterior never within localise_m)",
            len(never),
            ", ".join(never[:10]) + (" ..." if len(never) > 10 else ""),
        )
    res = _result(dataset, params, "pgp", a, final, cov, est)
    post = L.scatter(cfg, st)[inv] if posterior else np.zeros((0, 0, 0))
    info = PGPInfo(
        axis_m=np.asarray(lattice.axis(np.float64)),
        posterior=post,
        snapshot_epochs=np.zeros((0,), np.int64),
        snapshots=np.zeros((0, n, 0, 0)),
        log_mass=np.zeros(est.shape[:2]),
        raw_track=raw,
        localised=loc_any,
        frame=f"anchors:{b[0]},{b[1]},{b[2]}",
    )
    return res, info


def _filter_anchors(dataset: MeshDataset, anchors, mode: str) -> tuple[int, int, int]:
    """The frame the filter runs in (`PGPParams.frame`: "auto" or "proxy")."""
    from jaxcal.mesh import identify

    if mode == "proxy":
        best = identify.choose_frame(dataset.range)
        return anchors if best is None else best[0]
    return identify.filter_frame(dataset.range, anchors)


def _to_config_frame(final, cov, track, anchors):
    """(final, cov, track) of a proxy-frame run moved into the frame of `anchors` (2-D): each epoch of
    the track through that epoch's estimates of a0, a1, a2, the final position and covariance through
    the final ones (`frame.frame_covariance`, first order)."""
    from jaxcal.mesh.frame import frame_covariance, to_frame_track

    a0, a1, a2 = anchors
    track = to_frame_track(track, a0, a1, a2)
    out = to_frame_track(final[None], a0, a1, a2)[0]
    if np.isfinite(out).all(axis=1).any():
        c = np.where(np.isfinite(cov), cov, 0.0)
        cov = np.where(np.isfinite(out).all(axis=1)[:, None, None], frame_covariance(final, c, a0, a1, a2), np.nan)
    else:
        cov = np.full_like(cov, np.nan)
    return out, cov, track


def _software() -> str:
    try:
        from importlib.metadata import version

        return f"jaxcal {version('jaxcal')}"
    except Exception:  # noqa: BLE001 - metadata absent in a source checkout
        return "jaxcal"


def calibrate(dataset: MeshDataset, params=None, config: str | None = None, progress=None) -> Result:
    """`--method pgp`: the grid-based Bayesian filter with hypothesis likelihoods (eq. 3-14); nodes the
    ranges cannot fix in the frame (`identify.py`) are NaN rows, named in one warning line.

    `progress`: optional callback called with the epochs done since its last call."""
    from jaxcal.mesh.identify import mask_result

    res = run_pgp(dataset, params, config, mode="pgp", progress=progress, posterior=False)[0]
    return mask_result(with_pair_covariance(res, dataset.range), dataset.range)


def with_pair_covariance(res: Result, range_m: np.ndarray) -> Result:
    """`res` with each node's covariance widened, in every direction, to at least its covariance under
    per-pair systematic errors sized from the data (`pair_covariance.position_covariance`, least-squares
    influence, the unmodelled common range offset as one more shared error).

    The grid posterior multiplies the likelihoods of every epoch as if the ranges were independent, so
    it narrows with the number of epochs; a pair's offset (antenna delays, static multipath, an NLOS
    excess) is the same at every epoch and does not average out. Nodes the pairs do not fix keep the
    grid covariance (`identify.mask_result` decides what is reported)."""
    from jaxcal.mesh.batch import covariance_union
    from jaxcal.mesh.pair_covariance import position_covariance

    anchors = res.frame_anchors()
    if res.covariance is None or anchors is None or res.position.shape[1] != 2:
        return res
    pc = position_covariance(
        range_m, res.position, anchors, offset=False, robust_scale=float(res.params.get("sigma_r", 0.3))
    )
    cov = np.array(res.covariance, dtype=np.float64, copy=True)
    for k in range(cov.shape[0]):
        if np.isfinite(pc[k]).all() and np.isfinite(cov[k]).all():
            cov[k] = covariance_union(cov[k], pc[k])
    return eqx.tree_at(lambda r: r.covariance, res, cov)
