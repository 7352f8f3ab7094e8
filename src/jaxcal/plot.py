"""Figures of the papers (matplotlib): pure functions of arrays that return matplotlib Figures.

matplotlib is imported inside each function (so `import jaxcal` stays light) and figures are built
with the object-oriented API (`Figure`, never `pyplot`): no global state, no GUI backend;
`fig.savefig` renders with Agg. In a notebook a returned figure displays itself after
`%matplotlib inline`.

Units: metres everywhere. Every axis carries a label with its unit, every colour scale a colour bar.
Figure numbers in the docstrings refer to the grid-filter paper (000 in ../shared/papers).
The mesh figures live in `jaxcal.plot_mesh` and the shared style in `jaxcal.plot_style`; every figure is
imported from here.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from jaxcal.plot_mesh import (
    availability_bars,
    covariance_ellipse,
    node_error_distributions,
    positions_map,
    posterior_grids,
)
from jaxcal.plot_style import COLOURS, MARKERS, colour, figure, plain_log_axis, plain_log_ticks

__all__ = [
    "ranging_histograms",
    "qq_plot",
    "pairwise_rmse_matrix",
    "availability_bars",
    "node_error_distributions",
    "rmse_ecdfs",
    "positions_map",
    "posterior_grids",
    "trajectory_anchors",
    "sweep_surface",
    "covariance_ellipse",
]


def ranging_histograms(err: np.ndarray, los: np.ndarray, bins: int = 80):
    """Fig. 9: histograms of signed ranging errors for LOS, NLOS and all measurements.

    Args:
        err: (M,) signed ranging errors `range - true distance` [m].
        los: (M,) int labels (1 LOS, 0 NLOS, -1 unknown).
        bins: number of histogram bins over each panel's range.

    Returns:
        Figure with three panels (log count axis, so that the NLOS tail stays visible).
    """
    err = np.asarray(err, dtype=np.float64)
    los = np.asarray(los)
    fig = figure(12, 3.6)
    axes = fig.subplots(1, 3)
    groups = (
        ("LOS", los == 1, COLOURS[0]),
        ("NLOS", los == 0, COLOURS[1]),
        ("all", np.ones(err.size, bool), "0.35"),
    )
    for ax, (name, mask, shade) in zip(axes, groups, strict=True):
        x = err[mask & np.isfinite(err)]
        ax.set_title(f"{name} (n = {x.size:,})")
        ax.set_xlabel("range - true distance [m]")
        ax.set_ylabel("measurements")
        if x.size == 0:
            ax.text(0.5, 0.5, "no measurements", transform=ax.transAxes, ha="center", va="center")
            continue
        ax.hist(x, bins=bins, color=shade, alpha=0.85)
        ax.set_yscale("log")
        ax.axvline(0.0, color="k", lw=0.8, ls="--")
        a = np.abs(x)
        text = (
            f"mean {x.mean():+.2f} m\nmedian {np.median(x):+.2f} m\n"
            f"|e| 68.27 % {np.quantile(a, 0.6827):.2f} m\n"
            f"|e| 95.45 % {np.quantile(a, 0.9545):.2f} m"
        )
        ax.text(
            0.97,
            0.97,
            text,
            transform=ax.transAxes,
            ha="right",
            va="top",
            fontsize=8,
            bbox={"boxstyle": "round", "fc": "white", "ec": "0.7"},
        )
    return fig


def qq_plot(true_q: np.ndarray, measured_q: np.ndarray, r2_qq: float, r2: float | None = None):
    """Fig. 11a: quantiles of measured against true distances, with the straight-line fit's R^2.

    Args:
        true_q, measured_q: (Q,) quantiles at the same probabilities [m].
        r2_qq: coefficient of determination of the Q-Q line. r2: optional per-measurement R^2.

    Returns:
        Figure with one panel.
    """
    fig = figure(5.2, 4.6)
    ax = fig.subplots()
    t = np.asarray(true_q, dtype=np.float64)
    m = np.asarray(measured_q, dtype=np.float64)
    ax.scatter(t, m, s=14, color=COLOURS[0], label="quantiles", zorder=3)
    if t.size:
        lo, hi = float(min(t.min(), m.min())), float(max(t.max(), m.max()))
        ax.plot([lo, hi], [lo, hi], color="k", lw=0.8, ls="--", label="measured = true")
        if t.size > 1 and np.ptp(t) > 0:
            slope, icpt = np.polyfit(t, m, 1)
            ax.plot(
                [lo, hi],
                [icpt + slope * lo, icpt + slope * hi],
                color=COLOURS[1],
                lw=1.2,
                label=f"fit: slope {slope:.2f}, offset {icpt:+.2f} m",
            )
    title = f"Q-Q, $R^2$ = {r2_qq:.3f}"
    if r2 is not None and np.isfinite(r2):
        title += f" (per measurement {r2:.3f})"
    ax.set_title(title)
    ax.set_xlabel("true distance quantile [m]")
    ax.set_ylabel("measured range quantile [m]")
    ax.legend(loc="upper left", fontsize=8)
    ax.grid(alpha=0.3)
    return fig


def pairwise_rmse_matrix(rmse: np.ndarray, ids: Sequence[str]):
    """Fig. 11b: RMSE of range i -> j over epochs as a matrix (log colour scale, values printed).

    Args:
        rmse: (N, N) RMSE [m], NaN where the pair was never measured.
        ids: (N,) node ids.

    Returns:
        Figure with one panel and a colour bar; never-measured pairs are grey.
    """
    from matplotlib.colors import LogNorm

    r = np.asarray(rmse, dtype=np.float64)
    n = r.shape[0]
    size = max(4.8, 0.5 * n + 2.0)
    fig = figure(size + 1.2, size)
    ax = fig.subplots()
    fin = r[np.isfinite(r) & (r > 0)]
    vmin = max(float(fin.min()), 1e-3) if fin.size else 0.01
    vmax = max(float(fin.max()), vmin * 10) if fin.size else 1.0
    ax.set_facecolor("0.85")
    im = ax.imshow(np.where(r > 0, r, np.nan), cmap="viridis", norm=LogNorm(vmin=vmin, vmax=vmax))
    for i in range(n):
        for j in range(n):
            v = r[i, j]
            if np.isfinite(v):
                dark = np.log(v / vmin) < 0.6 * np.log(vmax / vmin)
                ax.text(
                    j,
                    i,
                    f"{v:.1f}" if v < 10 else f"{v:.0f}",
                    ha="center",
                    va="center",
                    fontsize=7 if n <= 14 else 5,
                    color="white" if dark else "black",
                )
    ax.set_xticks(range(n), ids, rotation=90)
    ax.set_yticks(range(n), ids)
    ax.set_xlabel("to node j")
    ax.set_ylabel("from node i")
    ax.set_title("pairwise ranging RMSE [m] (grey: never measured)")
    cb = fig.colorbar(im, ax=ax, label="RMSE of range i -> j [m]", shrink=0.85)
    plain_log_ticks(cb, vmin, vmax)
    return fig


def rmse_ecdfs(
    values: Mapping[str, np.ndarray],
    xlabel: str = "node RMSE [m]",
    title: str = "",
    log_x: bool = True,
):
    """Fig. 12b / 13b: empirical CDFs of errors, one curve per (method, configuration).

    Args:
        values: label -> (M,) errors [m] (NaN ignored).
        xlabel: axis label (with unit). title: panel title. log_x: logarithmic error axis.

    Returns:
        Figure with one panel; the legend gives each curve's median.
    """
    fig = figure(7.0, 4.4)
    ax = fig.subplots()
    for i, (label, v) in enumerate(values.items()):
        x = np.sort(np.asarray(v, dtype=np.float64).ravel())
        x = x[np.isfinite(x)]
        if x.size == 0:
            continue
        p = np.arange(1, x.size + 1) / x.size
        ax.step(
            np.maximum(x, 1e-3) if log_x else x,
            p,
            where="post",
            color=colour(i),
            ls=("-", "--", ":", "-.")[(i // len(COLOURS)) % 4],
            lw=1.6,
            label=f"{label} (median {np.median(x):.2f} m)",
        )
    if log_x:
        ax.set_xscale("log")
        plain_log_axis(ax.xaxis)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("empirical CDF")
    ax.set_title(title or "ECDF")
    ax.grid(which="both", alpha=0.25)
    ax.legend(fontsize=8, loc="lower right")
    return fig


def trajectory_anchors(
    path_xy: np.ndarray,
    anchor_truth: np.ndarray | None,
    ids: Sequence[str],
    estimates: Mapping[str, tuple[np.ndarray, np.ndarray | None]],
):
    """Anchors estimated from a trajectory, with 2-sigma error bars, over the platform's path (x-y).

    Args:
        path_xy: (P, 2+) platform positions [m]. anchor_truth: (A, 2+) surveyed anchors [m] or None.
        ids: (A,) anchor ids.
        estimates: label -> ((A, 2+) positions [m], (A, D, D) covariance [m^2] or None).

    Returns:
        Figure with two panels: the whole scene, and a zoom on the surveyed anchors (with truth).
    """
    path = np.asarray(path_xy, dtype=np.float64)
    at = None if anchor_truth is None else np.asarray(anchor_truth, dtype=np.float64)
    zoom = at is not None and np.isfinite(at[:, :2]).all(axis=1).any()
    fig = figure(14.0 if zoom else 8.5, 6.2)
    axes = fig.subplots(1, 2 if zoom else 1, squeeze=False)[0]
    for k, ax in enumerate(axes):
        ax.plot(path[:, 0], path[:, 1], color="0.6", lw=0.8, label="platform path")
        if at is not None:
            ax.scatter(
                at[:, 0],
                at[:, 1],
                marker="^",
                s=110,
                facecolor="none",
                edgecolor="k",
                linewidths=1.5,
                label="anchor truth",
                zorder=5,
            )
            for i, a in enumerate(ids):
                if np.isfinite(at[i, :2]).all():
                    off = ((8, 8), (8, -14), (-22, 8), (-22, -14))[i % 4]
                    ax.annotate(a, at[i, :2], xytext=off, textcoords="offset points", fontsize=9)
        for m, (label, (pos, cov)) in enumerate(estimates.items()):
            p = np.asarray(pos, dtype=np.float64)
            if cov is not None:
                c = np.asarray(cov, dtype=np.float64)
                sd = np.sqrt(np.maximum(np.stack([c[:, 0, 0], c[:, 1, 1]], axis=1), 0.0))
            else:
                sd = np.zeros((p.shape[0], 2))
            ax.errorbar(
                p[:, 0],
                p[:, 1],
                xerr=2 * sd[:, 0],
                yerr=2 * sd[:, 1],
                fmt=MARKERS[m % len(MARKERS)],
                color=colour(m),
                ms=6,
                capsize=3,
                lw=1.2,
                alpha=0.85,
                label=label + (" (±2σ)" if cov is not None else " (no covariance)"),
                zorder=4,
            )
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.grid(alpha=0.3)
        if k == 0:
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_title("anchors over the trajectory")
            ax.legend(fontsize=8, loc="best")
        else:
            assert at is not None  # the zoom panel exists only with a truth
            ok = np.isfinite(at[:, :2]).all(axis=1)
            lo, hi = at[ok, :2].min(axis=0), at[ok, :2].max(axis=0)
            c, h = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo)) + 2.0
            ax.set_xlim(c[0] - h, c[0] + h)
            ax.set_ylim(c[1] - h, c[1] + h)
            ax.set_aspect("equal")
            ax.set_title("zoom on the surveyed anchors (2 m margin)")
    return fig


def sweep_surface(
    sigma_r: np.ndarray,
    tau: np.ndarray,
    rmse: np.ndarray,
    title: str = "",
    label: str = "RMSE [m]",
):
    """A metric (default RMSE) over a sigma_r x tau parameter sweep: colour map, lowest cell marked.

    Args:
        sigma_r: (S,) ranging standard deviations [m]. tau: (T,) probability-mass fractions.
        rmse: (S, T) value of each cell (NaN: failed or not run; drawn grey), lower is better.
        title: panel title. label: colour-bar label with the unit of `rmse`.

    Returns:
        Figure with one panel and a colour bar.
    """
    s = np.asarray(sigma_r, dtype=np.float64)
    t = np.asarray(tau, dtype=np.float64)
    r = np.asarray(rmse, dtype=np.float64)
    from matplotlib.colors import LogNorm, Normalize

    fig = figure(6.4, 4.8)
    ax = fig.subplots()
    ax.set_facecolor("0.85")
    fin = r[np.isfinite(r)]
    # a few failed corners (RMSE of metres) would flatten the interesting low region: log scale
    wide = fin.size > 0 and fin.min() > 0 and fin.max() > 5 * fin.min()
    norm = LogNorm(fin.min(), fin.max()) if wide else (Normalize() if not fin.size else Normalize(fin.min(), fin.max()))
    im = ax.pcolormesh(
        np.arange(s.size + 1) - 0.5,
        np.arange(t.size + 1) - 0.5,
        r.T,
        cmap="viridis",
        norm=norm,
        shading="flat",
    )
    ax.set_xticks(range(s.size), [f"{v:g}" for v in s], rotation=45 if s.size > 8 else 0)
    ax.set_yticks(range(t.size), [f"{v:g}" for v in t])
    if r.size <= 100:  # small grids: the numbers themselves, dark on light cells and vice versa
        best = np.nanargmin(r) if fin.size else -1
        for k, ((i, j), v) in enumerate(np.ndenumerate(r)):
            ax.text(
                i,
                j + (0.22 if k == best else 0.0),
                "n/a" if not np.isfinite(v) else f"{v:.3g}",
                ha="center",
                va="center",
                fontsize=8 if r.size > 30 else 9,
                color="0.3" if not np.isfinite(v) else ("white" if norm(v) < 0.5 else "black"),
            )
    if np.isfinite(r).any():
        i, j = np.unravel_index(np.nanargmin(r), r.shape)
        ax.scatter(
            [i],
            [j - (0.12 if r.size <= 100 else 0.0)],
            marker="*",
            s=160,
            color="red",
            edgecolor="white",
            label=f"lowest: sigma_r {s[i]:g} m, tau {t[j]:g}: {r[i, j]:.3g}",
        )
        fig.legend(fontsize=8, loc="outside lower center")
    ax.set_xlabel("sigma_r [m]")
    ax.set_ylabel("tau (probability-mass fraction)")
    ax.set_title(title or f"{label} over the sweep")
    cb = fig.colorbar(im, ax=ax, label=label)
    if wide:
        plain_log_ticks(cb, fin.min(), fin.max())
    return fig
