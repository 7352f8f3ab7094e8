"""Mesh figures of `jaxcal.plot` (grid-filter paper, 000 in ../shared/papers): availability per node
(Fig. 10), per-node error distributions (Fig. 12a / 13a), final positions with confidence ellipses, and
posterior grids (Fig. 6 style). Pure functions of arrays returning matplotlib Figures; metres throughout."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from jaxcal.plot_style import MARKERS, colour, figure, plain_log_axis

__all__ = ["availability_bars", "node_error_distributions", "covariance_ellipse", "positions_map", "posterior_grids"]


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
    fig = figure(max(8.0, 0.6 * n + 2), 2.4 * max(len(methods), 1) + 0.6)
    axes = np.atleast_1d(fig.subplots(max(len(methods), 1), 1, sharex=True, squeeze=False)[:, 0])
    x = np.arange(n)
    for ax, method in zip(axes, methods, strict=True):
        confs = list(availability[method])
        w = 0.8 / max(len(confs), 1)
        for c, conf in enumerate(confs):
            a = 100.0 * np.asarray(availability[method][conf], dtype=np.float64)
            bars = ax.bar(x + (c - (len(confs) - 1) / 2) * w, a, width=w, color=colour(c), label=conf)
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
    fig = figure(max(8.0, 0.75 * n + 2), 4.2)
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
                    color=colour(c),
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
                box.set(facecolor=colour(c), alpha=0.45, edgecolor=colour(c))
            for part in ("medians", "whiskers", "caps"):
                for line in bp[part]:
                    line.set(color=colour(c))
            rms = [float(np.sqrt(np.mean(d * d))) for d in data]
            ax.scatter(
                where,
                rms,
                marker="D",
                s=18,
                color=colour(c),
                edgecolor="k",
                linewidth=0.5,
                zorder=4,
            )
        from matplotlib.patches import Patch

        handles.append(Patch(facecolor=colour(c), alpha=0.6, label=conf))
    from matplotlib.lines import Line2D

    handles.append(Line2D([], [], marker="D", ls="", color="0.5", markeredgecolor="k", label="node RMSE"))
    ax.set_yscale("log")
    lows = [
        np.nanpercentile(np.asarray(e, dtype=np.float64), 5)
        for e in errors.values()
        if np.isfinite(np.asarray(e, dtype=np.float64)).any()
    ]
    ax.set_ylim(max(1e-3, 0.3 * min(lows)) if lows else 1e-3, None)
    plain_log_axis(ax.yaxis)
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
    fig = figure(min(6.0 * ratio, 12.0) + 0.8, 6.0 + 0.25 * (len(estimates) + 2) // 2)
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
            color=colour(m),
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
                        color=colour(m),
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
    fig = figure(2.9 * s_n + 1.2, 2.8 * m_n + 0.4)
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
