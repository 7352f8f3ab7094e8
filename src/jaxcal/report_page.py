"""HTML building blocks of `jaxcal.report`: number formatting, tables, and the page that collects
figures (saved as PNG at once, atomically) and sections."""

from __future__ import annotations

import html
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["CSS", "Page", "fmt", "slug", "table"]


def slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "x"


def fmt(v: Any, digits: int = 2) -> str:
    if v is None:
        return "–"
    if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
        return f"{int(v):,}"
    v = float(v)
    if not math.isfinite(v):
        return "–"
    return f"{v:,.{digits}f}"


def table(head: Sequence[str], rows: Sequence[Sequence[str]], cls: str = "") -> str:
    h = "".join(f"<th>{html.escape(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}"><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>'


class Page:
    """Collects figures (saved as PNG at once) and HTML sections."""

    def __init__(self, out: Path, dpi: int):
        self.out, self.dpi = out, dpi
        self.parts: list[str] = []
        self.figures: list[str] = []

    def h2(self, text: str) -> None:
        self.parts.append(f"<h2>{html.escape(text)}</h2>")

    def p(self, text: str) -> None:
        self.parts.append(f"<p>{html.escape(text)}</p>")

    def raw(self, text: str) -> None:
        self.parts.append(text)

    def figure(self, fig, name: str, caption: str) -> None:
        fname = f"{slug(name)}.png"
        from jaxcal.io.atomic import atomic_path

        with atomic_path(self.out / fname) as tmp:  # an interrupted report leaves no torn PNG
            fig.savefig(tmp, dpi=self.dpi, format="png")
        self.figures.append(fname)
        self.parts.append(
            f'<figure><img src="{html.escape(fname)}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>"
        )


CSS = """body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;
color:#222}table{border-collapse:collapse;margin:.6em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em}
table.num td{text-align:right}table.num td:first-child{text-align:left}th{background:#f0f0f0}
figure{margin:1.2em 0}img{max-width:100%;border:1px solid #eee}figcaption{font-size:.9em;color:#555}
details{margin:.5em 0}"""
