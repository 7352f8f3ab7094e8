"""Figures of the papers (matplotlib): pure functions of arrays that return matplotlib Figures.

matplotlib is imported inside each function (so `import jaxcal` stays light) and figures are built
with the object-oriented API (`Figure`, never `pyplot`): no global state, no GUI backend;
`fig.savefig` renders with Agg. In a notebook a returned figure displays itself after
`%matplotlib inline`.

Units: metres everywhere. Every axis carries a label with its unit, every colour scale a colour bar.
Figure numbers in the docstrings refer to the grid-filter paper (000 in ../shared/papers).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

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

# a colour-blind-safe qualitative cycle (Okabe-Ito), enough for methods x configurations
COLOURS = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#F0E442", "#000000")
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")


def _figure(width: float, height: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=100, layout="constrained")


def _colour(i: int) -> str:
    return COLOURS[i % len(COLOURS)]


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
    fig = _figure(12, 3.6)
    axes = fig.subplots(1, 3)
    groups = (
        ("LOS", los == 1, COLOURS[0]),
        ("NLOS", los == 0, COLOURS[1]),
        ("all", np.ones(err.size, bool), "0.35"),
    )
    for ax, (name, mask, colour) in zip(axes, groups, strict=True):
        x = err[mask & np.isfinite(err)]
        ax.set_title(f"{name} (n = {x.size:,})")
        ax.set_xlabel("range - true distance [m]")
        ax.set_ylabel("measurements")
        if x.size == 0:
            ax.text(0.5, 0.5, "no measurements", transform=ax.transAxes, ha="center", va="center")
            continue
        ax.hist(x, bins=bins, color=colour, alpha=0.85)
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
    fig = _figure(5.2, 4.6)
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
    fig = _figure(size + 1.2, size)
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
    _plain_log_ticks(cb, vmin, vmax)
    return fig


def _plain_log_axis(axis) -> None:
    """Tick labels of a logarithmic axis as plain numbers (0.01, 0.1, 1, 10), not 10^x."""
    from matplotlib.ticker import LogLocator, NullFormatter, StrMethodFormatter

    axis.set_major_locator(LogLocator(base=10.0))
    axis.set_major_formatter(StrMethodFormatter("{x:g}"))
    axis.set_minor_formatter(NullFormatter())


def _plain_log_ticks(cb, vmin: float, vmax: float) -> None:
    """Colour bar ticks at 1-2-5 steps written as plain numbers (not 10^x)."""
    from matplotlib.ticker import FixedLocator, NullFormatter, StrMethodFormatter

    steps = [m * 10.0**e for e in range(-4, 5) for m in (1, 2, 5)]
    ticks = [v for v in steps if vmin <= v <= vmax] or [vmin, vmax]
    cb.ax.yaxis.set_major_locator(FixedLocator(ticks))
    cb.ax.yaxis.set_major_formatter(StrMethodFormatter("{x:g}"))
    cb.ax.yaxis.set_minor_formatter(NullFormatter())


def availability_bars(ids: Sequence[str], availability: Mapping[str, Mapping[str, np.ndarray]]):
    """Fig. 10: share of epochs with a position estimate per node, per method and configuration.

    Args:
        ids: (N,) node ids.
        availability: method -> {configuration -> (N,) availability in [0, 1]}.

    Returns:
        Figure with one row of bars per method, configurations side by side.
    """
    methods = list(availability)
    n = len(ids)
    fig = _figure(max(8.0, 0.6 * n + 2), 2.4 * max(len(methods), 1) + 0.6)
    axes = np.atleast_1d(fig.subplots(max(len(methods), 1), 1, sharex=True, squeeze=False)[:, 0])
    x = np.arange(n)
    for ax, method in zip(axes, methods, strict=True):
        confs = list(availability[method])
        w = 0.8 / max(len(confs), 1)
        for c, conf in enumerate(confs):
            a = 100.0 * np.asarray(availability[method][conf], dtype=np.float64)
            bars = ax.bar(x + (c - (len(confs) - 1) / 2) * w, a, width=w, color=_colour(c), label=conf)
            for b, v in zip(bars, a, strict=True):
                if np.isfinite(v) and v < 95:
                    ax.text(
                        b.get_x() + b.get_width() / 2,
                        v + 2,
                        f"{v:.0f}",
                        ha="center",
                        va="bottom",
                        fontsize=7,
                    )
        ax.set_ylim(0, 132)  # headroom above 100 % for the legend
        ax.set_yticks([0, 20, 40, 60, 80, 100])
        ax.set_ylabel("availability [%]")
        ax.set_title(f"{method}: epochs with an estimate per node", fontsize=10)
        ax.legend(loc="upper right", fontsize=8, ncols=len(confs))
        ax.grid(axis="y", alpha=0.3)
    axes[-1].set_xticks(x, ids, rotation=45)
    axes[-1].set_xlabel("node")
    return fig


def node_error_distributions(
    ids: Sequence[str],
    errors: Mapping[str, np.ndarray],
    title: str = "",
    origin: Mapping[str, int] | None = None,
):
    """Fig. 12a / 13a: per-node distribution of position errors over epochs, configurations abreast.

    Args:
        ids: (N,) node ids.
        errors: configuration -> (K, N) position error per epoch and node [m] (NaN: no estimate).
        title: panel title (e.g. the method).
        origin: configuration -> index of its a0 (the frame's origin, no error by construction),
            or None.

    Returns:
        Figure: boxes (5-95 % whiskers) of the per-epoch errors on a log axis, with each node's RMSE
        as a diamond; nodes without any estimate are marked "n/a".
    """
    n = len(ids)
    confs = list(errors)
    fig = _figure(max(8.0, 0.75 * n + 2), 4.2)
    ax = fig.subplots()
    w = 0.8 / max(len(confs), 1)
    x = np.arange(n)
    handles: list = []  # legend artists: Patch and Line2D
    for c, conf in enumerate(confs):
        e = np.asarray(errors[conf], dtype=np.float64)
        if e.ndim == 1:
            e = e[None]
        pos = x + (c - (len(confs) - 1) / 2) * w
        data, where = [], []
        for i in range(n):
            v = e[:, i][np.isfinite(e[:, i])]
            if v.size:
                data.append(np.maximum(v, 1e-3))
                where.append(pos[i])
            else:
                ax.text(
                    pos[i],
                    0.02,
                    "a0" if origin is not None and origin.get(conf) == i else "none",
                    transform=ax.get_xaxis_transform(),
                    ha="center",
                    va="bottom",
                    fontsize=7,
                    rotation=90,
                    color=_colour(c),
                )
        if data:
            bp = ax.boxplot(
                data,
                positions=where,
                widths=w * 0.85,
                whis=(5, 95),
                showfliers=False,
                patch_artist=True,
                manage_ticks=False,
            )
            for box in bp["boxes"]:
                box.set(facecolor=_colour(c), alpha=0.45, edgecolor=_colour(c))
            for part in ("medians", "whiskers", "caps"):
                for line in bp[part]:
                    line.set(color=_colour(c))
            rms = [float(np.sqrt(np.mean(d * d))) for d in data]
            ax.scatter(
                where,
                rms,
                marker="D",
                s=18,
                color=_colour(c),
                edgecolor="k",
                linewidth=0.5,
                zorder=4,
            )
        from matplotlib.patches import Patch

        handles.append(Patch(facecolor=_colour(c), alpha=0.6, label=conf))
    from matplotlib.lines import Line2D

    handles.append(Line2D([], [], marker="D", ls="", color="0.5", markeredgecolor="k", label="node RMSE"))
    ax.set_yscale("log")
    lows = [
        np.nanpercentile(np.asarray(e, dtype=np.float64), 5)
        for e in errors.values()
        if np.isfinite(np.asarray(e, dtype=np.float64)).any()
    ]
    ax.set_ylim(max(1e-3, 0.3 * min(lows)) if lows else 1e-3, None)
    _plain_log_axis(ax.yaxis)
    ax.set_xlim(-0.6, n - 0.4)
    ax.set_xticks(x, ids, rotation=45)
    ax.set_xlabel("node")
    ax.set_ylabel("position error per epoch [m]")
    ax.set_title(
        (title + "\n" if title else "")
        + "boxes 25-75 %, whiskers 5-95 %; 'none': no estimate; a0: origin of the frame",
        fontsize=10,
    )
    ax.legend(handles=handles, fontsize=8, loc="upper left", ncols=len(handles))
    ax.grid(axis="y", which="both", alpha=0.25)
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
    fig = _figure(7.0, 4.4)
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
            color=_colour(i),
            ls=("-", "--", ":", "-.")[(i // len(COLOURS)) % 4],
            lw=1.6,
            label=f"{label} (median {np.median(x):.2f} m)",
        )
    if log_x:
        ax.set_xscale("log")
        _plain_log_axis(ax.xaxis)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("empirical CDF")
    ax.set_title(title or "ECDF")
    ax.grid(which="both", alpha=0.25)
    ax.legend(fontsize=8, loc="lower right")
    return fig


def covariance_ellipse(cov: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """Semi-axes [m] and angle [deg] of the `level` confidence ellipse of a 2-D Gaussian.

    Args:
        cov: (2, 2) covariance [m^2]. level: probability mass inside the ellipse.

    Returns:
        (a, b, angle_deg): semi-major, semi-minor axis and rotation of the major axis from +x.
    """
    c = np.asarray(cov, dtype=np.float64)[:2, :2]
    c = 0.5 * (c + c.T)
    k2 = -2.0 * np.log1p(-level)  # chi-square quantile with 2 degrees of freedom
    w, v = np.linalg.eigh(c)
    w = np.maximum(w, 0.0)
    a, b = np.sqrt(k2 * w[1]), np.sqrt(k2 * w[0])
    return float(a), float(b), float(np.degrees(np.arctan2(v[1, 1], v[0, 1])))


def positions_map(
    truth: np.ndarray,
    ids: Sequence[str],
    estimates: Mapping[str, tuple[np.ndarray, np.ndarray | None]],
    title: str = "",
    level: float = 0.95,
):
    """Final positions of every method with `level` uncertainty ellipses over the truth (one frame).

    Args:
        truth: (N, 2+) true positions in the estimates' frame [m] (first two axes drawn).
        ids: (N,) node ids.
        estimates: label -> ((N, 2+) positions [m], (N, D, D) covariance [m^2] or None).
        title: panel title (e.g. the frame). level: ellipse probability mass.

    Returns:
        Figure with one panel; the view is the truth's extent plus a margin, and estimates outside
        it are counted in the legend.
    """
    from matplotlib.patches import Ellipse

    t = np.asarray(truth, dtype=np.float64)[:, :2]
    ok = np.isfinite(t).all(axis=1)
    lo, hi = t[ok].min(axis=0), t[ok].max(axis=0)
    size = float(max(np.max(hi - lo), 1.0))
    # the view holds the truth and every estimate within one truth extent of it; farther ones are
    # counted
    near_lo, near_hi = lo - size, hi + size
    for pos, _ in estimates.values():
        p = np.asarray(pos, dtype=np.float64)[:, :2]
        p = p[np.isfinite(p).all(axis=1) & (p >= near_lo).all(axis=1) & (p <= near_hi).all(axis=1)]
        if p.size:
            lo, hi = np.minimum(lo, p.min(axis=0)), np.maximum(hi, p.max(axis=0))
    pad = 0.08 * float(max(np.max(hi - lo), 1.0))
    lo, hi = lo - pad, hi + pad
    ratio = float(np.clip((hi[0] - lo[0]) / (hi[1] - lo[1]), 0.5, 2.5))
    fig = _figure(min(6.0 * ratio, 12.0) + 0.8, 6.0 + 0.25 * (len(estimates) + 2) // 2)
    ax = fig.subplots()
    ax.scatter(t[ok, 0], t[ok, 1], marker="x", s=70, color="k", linewidths=1.8, label="truth", zorder=5)
    for i in np.flatnonzero(ok):
        ax.annotate(ids[int(i)], t[i], xytext=(5, 5), textcoords="offset points", fontsize=8)
    for m, (label, (pos, cov)) in enumerate(estimates.items()):
        p = np.asarray(pos, dtype=np.float64)[:, :2]
        fin = np.isfinite(p).all(axis=1)
        inside = fin & (p >= lo).all(axis=1) & (p <= hi).all(axis=1)
        n_out = int((fin & ~inside).sum())
        extra = f", {n_out} outside view" if n_out else ""
        extra += "" if cov is not None else ", no covariance"
        ax.scatter(
            p[inside, 0],
            p[inside, 1],
            marker=MARKERS[m % len(MARKERS)],
            s=28,
            color=_colour(m),
            alpha=0.9,
            label=f"{label}{extra}",
            zorder=4,
        )
        if cov is not None:
            c = np.asarray(cov, dtype=np.float64)
            for i in np.flatnonzero(inside & np.isfinite(c[:, :2, :2]).all(axis=(1, 2))):
                a, b, ang = covariance_ellipse(c[i], level)
                ax.add_patch(
                    Ellipse(
                        p[i],
                        2 * max(a, 0.05),
                        2 * max(b, 0.05),
                        angle=ang,
                        fill=False,
                        color=_colour(m),
                        lw=1.0,
                        alpha=0.9,
                    )
                )
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title((title + ": " if title else "") + f"final positions, {100 * level:.0f} % ellipses")
    ax.grid(alpha=0.3)
    fig.legend(*ax.get_legend_handles_labels(), fontsize=8, loc="outside lower center", ncols=2)
    return fig


def posterior_grids(
    axis_m: np.ndarray,
    grids: np.ndarray,
    node_ids: Sequence[str],
    epochs: Sequence[int] | np.ndarray,
    truth: np.ndarray | None = None,
    estimates: np.ndarray | None = None,
    floor: float = 1e-6,
):
    """Fig. 6 style: posterior grids of chosen nodes (rows) at chosen epochs (columns).

    Args:
        axis_m: (n,) cell-centre coordinates of both grid axes [m].
        grids: (S, M, n, n) probabilities, `grids[s, m, ix, iy]` at `(axis_m[ix], axis_m[iy])`,
            for the S epochs and M nodes.
        node_ids: (M,) ids of the rows. epochs: (S,) epoch indices of the columns.
        truth: (M, 2+) true positions in the grid's frame [m], or None.
        estimates: (S, M, 2) the filter's estimates at those epochs [m] (NaN: none), or None.
        floor: smallest probability shown on the logarithmic colour scale.

    Returns:
        Figure with M x S panels sharing one logarithmic colour bar; each row is zoomed to the cells
        above 1e-4 at any of its epochs and the truth, with a 3 m margin.
    """
    from matplotlib.colors import LogNorm

    g = np.asarray(grids, dtype=np.float64)
    s_n, m_n = g.shape[0], g.shape[1]
    ax_m = np.asarray(axis_m, dtype=np.float64)
    half = 0.5 * (ax_m[1] - ax_m[0]) if ax_m.size > 1 else 0.5
    extent = (ax_m[0] - half, ax_m[-1] + half, ax_m[0] - half, ax_m[-1] + half)
    fig = _figure(2.9 * s_n + 1.2, 2.8 * m_n + 0.4)
    axes = fig.subplots(m_n, s_n, squeeze=False)
    norm = LogNorm(vmin=floor, vmax=1.0)
    im = None
    for r in range(m_n):
        ix, iy = np.nonzero((g[:, r] > 1e-4).any(axis=0))
        xs = list(ax_m[ix]) if ix.size else list(ax_m[[0, -1]])
        ys = list(ax_m[iy]) if iy.size else list(ax_m[[0, -1]])
        if truth is not None and np.isfinite(truth[r, :2]).all():
            xs.append(truth[r, 0])
            ys.append(truth[r, 1])
        cx, cy = 0.5 * (min(xs) + max(xs)), 0.5 * (min(ys) + max(ys))
        h = 0.5 * max(max(xs) - min(xs), max(ys) - min(ys)) + 3.0
        # keep the square view inside the grid: outside it there is no posterior to show
        h = min(h, 0.5 * (extent[1] - extent[0]))
        cx = float(np.clip(cx, extent[0] + h, extent[1] - h))
        cy = float(np.clip(cy, extent[2] + h, extent[3] - h))
        for c in range(s_n):
            ax = axes[r, c]
            p = np.clip(g[c, r].T, floor, 1.0)  # rows of imshow are y
            im = ax.imshow(p, origin="lower", extent=extent, cmap="magma", norm=norm, interpolation="nearest")
            if truth is not None and np.isfinite(truth[r, :2]).all():
                ax.scatter([truth[r, 0]], [truth[r, 1]], marker="x", s=60, color="cyan", linewidths=1.8)
            if estimates is not None and np.isfinite(estimates[c, r, :2]).all():
                ax.scatter(
                    [estimates[c, r, 0]],
                    [estimates[c, r, 1]],
                    marker="+",
                    s=70,
                    color="lime",
                    linewidths=1.5,
                )
            ax.set_xlim(cx - h, cx + h)
            ax.set_ylim(cy - h, cy + h)
            ax.set_title(f"{node_ids[r]}, epoch {int(epochs[c])}", fontsize=9)
            ax.set_xlabel("x [m]", fontsize=8)
            ax.set_ylabel("y [m]", fontsize=8)
            ax.tick_params(labelsize=7)
    if im is not None:
        fig.colorbar(im, ax=axes, label="posterior probability per cell", shrink=0.9)
    fig.suptitle(
        "posterior grids (cyan x: truth" + (", green +: estimate)" if estimates is not None else ")"),
        fontsize=10,
    )
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
    fig = _figure(14.0 if zoom else 8.5, 6.2)
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
                color=_colour(m),
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

    fig = _figure(6.4, 4.8)
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
        _plain_log_ticks(cb, fin.min(), fin.max())
    return fig
