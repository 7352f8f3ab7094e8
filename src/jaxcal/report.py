"""Report folders: the papers' figures as PNG files and an `index.html` showing them with numbers.

`write_report(results, truth_dataset, out_dir)` is the one call (used by `jaxcal report` and
`jaxcal demo`). It groups results by (method, configuration): a mesh result's configuration is the
name in the dataset's `configs` whose (a0, a1, a2) equals the result's frame (else the frame
string), a trajectory result's is its frame (`world`). What it draws depends on what is there:

- a dataset with truth: Table I (HTML), ranging residual histograms LOS / NLOS / all (Fig. 9), the
  Q-Q plot with R^2 (Fig. 11a) and, for mesh data, the pairwise RMSE matrix (Fig. 11b);
- mesh results: a summary table, availability per node and configuration (Fig. 10, results with a
  track), per-node error distributions per method with configurations side by side (Fig. 12a /
  13a), ECDFs of node RMSE and of per-epoch errors of every group (Fig. 12b / 13b), final
  positions with 95 % ellipses from the result's covariance over the truth (one figure per frame);
- posterior grids (Fig. 6 style): PGP results do not store grids, so the report re-runs the PGP
  filter (`jaxcal.mesh.pgp.run_pgp`, with the result's own parameters and frame) on the first
  epochs of the dataset, up to the last requested epoch. The filter is causal, so the grid at
  epoch k of this short run is the grid at epoch k of the full run. `posteriors="auto"` (default)
  picks the first `pgp` result, the nodes a2, the best and the worst non-frame node by final
  error, and epochs 3, 10, 30, 100 (those that exist); a `PosteriorSpec` names nodes and epochs;
  `"none"` skips the figure;
- trajectory results: anchors with 2-sigma error bars over the platform path and a table of
  anchor errors;
- sweeps (`sweeps=[{"sigma_r", "tau", "rmse", "title", ...}]`, e.g. from `sweep_surfaces` of a
  `jaxcal sweep` file): the RMSE (or another metric) surface over sigma_r x tau, figure and
  table. No truth dataset is needed for a report of sweeps only.

Numbers also go to `report.json` next to `index.html`.
"""

from __future__ import annotations

import html
import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from jaxcal.data import MeshDataset, Result, TrajectoryDataset
from jaxcal.errors import JaxcalError
from jaxcal.io.jsonsafe import json_safe
from jaxcal.report_page import CSS, Page
from jaxcal.report_sections import (
    AUTO_POSTERIOR_EPOCHS,
    PosteriorSpec,
    group_label,
    mesh_section,
    parse_posteriors,
    posterior_section,
    ranging_section,
    trajectory_section,
)
from jaxcal.report_sweep import SWEEP_METRICS, sweep_section, sweep_surfaces

__all__ = [
    "PosteriorSpec",
    "parse_posteriors",
    "group_label",
    "sweep_surfaces",
    "write_report",
    "AUTO_POSTERIOR_EPOCHS",
    "SWEEP_METRICS",
]


def report_sections(has_truth: bool, n_results: int, mesh: bool, n_sweeps: int) -> int:
    """Sections `write_report` reports to its `progress` callback."""
    return int(has_truth) + (0 if not n_results else (2 if mesh else 1)) + int(n_sweeps > 0)


def write_report(
    results: Sequence[Result],
    truth_dataset: MeshDataset | TrajectoryDataset | None,
    out_dir: str | Path,
    *,
    labels: Sequence[str] | None = None,
    posteriors: str | PosteriorSpec = "auto",
    sweeps: Sequence[Mapping[str, Any]] = (),
    title: str | None = None,
    dpi: int = 110,
    progress: Callable[[int], None] | None = None,
) -> Path:
    """Write PNG figures, `index.html` and `report.json` for results against a dataset's truth.

    Args:
        results: calibration results of the dataset (mesh or trajectory, not mixed).
        truth_dataset: the dataset the results came from, with truth (None: sweeps only).
        out_dir: folder to write (created).
        labels: one label per result; default `method/configuration` (duplicates get `#2`, `#3`).
        posteriors: "auto", "none" or a `PosteriorSpec` (see the module docstring).
        sweeps: dicts with `sigma_r` (S,) [m], `tau` (T,), `rmse` (S, T) [m] and optional `title`;
            optional `metric` / `label` when the values are another metric, and the counts and
            `best_others` of `sweep_surfaces` (shown in the table).
        title: page title. dpi: PNG resolution.
        progress: called with 1 after each section (`report_sections(...)` calls in all).

    Returns:
        Path of `index.html`.
    """
    from jaxcal.metrics import evaluate

    ds = truth_dataset
    if not results and not sweeps:
        raise JaxcalError("nothing to report: no results")
    if ds is None and results:
        raise JaxcalError("calibration results need the truth dataset (--truth)")
    mesh = isinstance(ds, MeshDataset)
    if ds is not None and (ds.truth if isinstance(ds, MeshDataset) else ds.anchor_truth) is None:
        raise JaxcalError(f"{ds.name}: the truth dataset has no ground truth")
    if labels is not None and len(labels) != len(results):
        raise JaxcalError(f"labels: {len(labels)} given for {len(results)} results")
    for r in results:
        if mesh != (r.frame_anchors() is not None):
            raise JaxcalError(
                f"result {r.name or r.method!r} (frame {r.frame}) does not fit a "
                f"{'mesh' if mesh else 'trajectory'} truth dataset"
            )
    groups: dict[str, Result] = {}
    for i, r in enumerate(results):
        lab = labels[i] if labels is not None else group_label(r, ds)
        base, n = lab, 2
        while lab in groups:
            lab, n = f"{base}#{n}", n + 1
        groups[lab] = r
    evals = {lab: evaluate(r, ds) for lab, r in groups.items()} if ds is not None else {}

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    page = Page(out, dpi)
    numbers: dict[str, Any] = {"dataset": None if ds is None else ds.name, "groups": {}}
    done = progress or (lambda k: None)
    if ds is not None:
        ranging_section(page, ds, numbers)
        done(1)
    if groups:
        if isinstance(ds, MeshDataset):
            mesh_section(page, ds, groups, evals, numbers)
            done(1)
            posterior_section(page, ds, groups, evals, posteriors, numbers)
            done(1)
        elif isinstance(ds, TrajectoryDataset):
            trajectory_section(page, ds, groups, evals, numbers)
            done(1)
    for lab, ev in evals.items():
        numbers["groups"][lab] = {k: v for k, v in ev.items() if k != "ecdf"}
    if sweeps:
        sweep_section(page, sweeps, numbers)
        done(1)
    numbers["figures"] = page.figures
    head = title or f"jaxcal report: {ds.name if ds is not None else 'parameter sweeps'}"
    if ds is None:
        meta = f"{len(sweeps)} sweep surface(s), no dataset"
    else:
        meta = (
            f"dataset {ds.name}: "
            + (
                f"{ds.n_nodes} nodes, {ds.n_epochs} epochs"
                if isinstance(ds, MeshDataset)
                else f"{len(ds.anchor_ids)} anchors, {ds.range.size:,} ranges"
            )
            + f"; results: {', '.join(groups) or 'none'}"
        )
    doc = (
        f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(head)}</title>"
        f"<style>{CSS}</style></head><body><h1>{html.escape(head)}</h1><p>{html.escape(meta)}</p>"
        + "\n".join(page.parts)
        + "</body></html>\n"
    )
    from jaxcal.io.atomic import atomic_write_text

    atomic_write_text(out / "report.json", json.dumps(json_safe(numbers), indent=1, allow_nan=False))
    index = out / "index.html"
    atomic_write_text(index, doc)
    return index
