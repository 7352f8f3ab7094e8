"""Shared style of `jaxcal.plot`'s figures: the colour-blind-safe colours and markers, the figure
factory (object-oriented matplotlib, constrained layout, no pyplot) and plain-number log ticks."""

from __future__ import annotations

__all__ = ["COLOURS", "MARKERS", "colour", "figure", "plain_log_axis", "plain_log_ticks"]

# a colour-blind-safe qualitative cycle (Okabe-Ito), enough for methods x configurations
COLOURS = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#F0E442", "#000000")
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")


def figure(width: float, height: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=100, layout="constrained")


def colour(i: int) -> str:
    return COLOURS[i % len(COLOURS)]


def plain_log_axis(axis) -> None:
    """Tick labels of a logarithmic axis as plain numbers (0.01, 0.1, 1, 10), not 10^x."""
    from matplotlib.ticker import LogLocator, NullFormatter, StrMethodFormatter

    axis.set_major_locator(LogLocator(base=10.0))
    axis.set_major_formatter(StrMethodFormatter("{x:g}"))
    axis.set_minor_formatter(NullFormatter())


def plain_log_ticks(cb, vmin: float, vmax: float) -> None:
    """Colour bar ticks at 1-2-5 steps written as plain numbers (not 10^x)."""
    from matplotlib.ticker import FixedLocator, NullFormatter, StrMethodFormatter

    steps = [m * 10.0**e for e in range(-4, 5) for m in (1, 2, 5)]
    ticks = [v for v in steps if vmin <= v <= vmax] or [vmin, vmax]
    cb.ax.yaxis.set_major_locator(FixedLocator(ticks))
    cb.ax.yaxis.set_major_formatter(StrMethodFormatter("{x:g}"))
    cb.ax.yaxis.set_minor_formatter(NullFormatter())
