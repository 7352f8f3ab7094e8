"""PGP's user-facing parameters (`PGPParams`, the `--set` keys) and their validation."""

from __future__ import annotations

import math

import equinox as eqx

from jaxcal.errors import JaxcalError

__all__ = [
    "PGPParams",
    "validate_params",
    "BIASES",
    "OFFSET_EPOCHS",
    "GRID_MODES",
    "FRAMES",
    "LIKELIHOODS",
    "RANGE_MODELS",
    "NUMERIC",
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
        frame: which frame the filter runs in (`frame_choice.filter_frame`): "auto" (default) the
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
        mirror: "check" (default): after the filter, parts of the layout locked in a mirror image are
            moved to the image the pair medians prefer, and nodes whose image they leave undecided are
            unplaced (`mirror.py`; issue #24: a part that localised on the wrong side of a hinge early
            stays there); "off": the filter's layout as it ends.
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
    mirror: str = "check"


BIASES = ("auto", "none", "network")
MIRRORS = ("check", "off")
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


def validate_params(params: PGPParams) -> None:
    """Raise a one-line `JaxcalError` naming the first parameter of `params` out of its range."""
    p = params

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
    need(p.mirror in MIRRORS, f"mirror: one of {', '.join(MIRRORS)}; got {p.mirror!r}")
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
