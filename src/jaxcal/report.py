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

import dataclasses
import html
import json
import math
import re
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxcal.data import MeshDataset, Result, TrajectoryDataset
from jaxcal.errors import JaxcalError
from jaxcal.io.jsonsafe import json_safe

__all__ = [
    "PosteriorSpec",
    "parse_posteriors",
    "group_label",
    "sweep_surfaces",
    "write_report",
    "AUTO_POSTERIOR_EPOCHS",
    "SWEEP_METRICS",
]

AUTO_POSTERIOR_EPOCHS = (3, 10, 30, 100)
TABLE_KEYS = (
    ("share", "share", 3),
    ("count", "count", 0),
    ("mean_m", "mean [m]", 2),
    ("median_m", "median [m]", 2),
    ("variance_m2", "var [m²]", 2),
    ("q1sigma_m", "1σ [m]", 2),
    ("q2sigma_m", "2σ [m]", 2),
    ("q3sigma_m", "3σ [m]", 2),
    ("p25_m", "25 % [m]", 2),
    ("p50_m", "50 % [m]", 2),
    ("p75_m", "75 % [m]", 2),
)


# metrics of a `jaxcal sweep` file drawn as surfaces (lower is better) and their labels
SWEEP_METRICS = {
    "rmse_m": "RMSE [m]",
    "final_rmse_m": "final RMSE [m]",
    "nlpl": "NLPL [nats per range]",
}


@dataclasses.dataclass(frozen=True)
class PosteriorSpec:
    """Which posterior grids to draw: node ids (rows) at epochs (columns); `method`: the result."""

    nodes: tuple[str, ...]
    epochs: tuple[int, ...]
    method: str = "pgp"


def parse_posteriors(text: str | None) -> str | PosteriorSpec:
    """`auto`, `none` or `NODE[,NODE...]@EPOCH[,EPOCH...]` (e.g. `D5B4,9911@5,20,100`)."""
    if text is None or text.strip().lower() in ("", "auto"):
        return "auto"
    if text.strip().lower() == "none":
        return "none"
    nodes, sep, epochs = text.partition("@")
    try:
        ep = tuple(int(e) for e in epochs.split(",") if e.strip())
    except ValueError:
        ep = ()
    nd = tuple(n.strip() for n in nodes.split(",") if n.strip())
    if not sep or not nd or not ep or min(ep) < 0:
        raise JaxcalError(f"--posteriors: expected auto, none or NODE,...@EPOCH,... (epochs >= 0), got {text!r}")
    return PosteriorSpec(nd, ep)


def _axis(runs: Mapping[str, np.ndarray], name: str, fixed: Mapping[str, float], n: int) -> np.ndarray:
    if f"param_{name}" in runs:
        return np.asarray(runs[f"param_{name}"], dtype=np.float64)
    if name not in fixed:
        raise JaxcalError(f"sweep: {name} is neither swept nor given as a fixed value")
    return np.full(n, float(fixed[name]))


def sweep_surfaces(
    runs: Mapping[str, np.ndarray],
    metrics: Mapping[str, np.ndarray],
    done: np.ndarray,
    *,
    metric: str = "rmse_m",
    others: str = "best",
    fixed: Mapping[str, float] | None = None,
    method: str = "",
) -> list[dict[str, Any]]:
    """Surfaces over sigma_r x tau of the runs of a parameter sweep (the layout of `jaxcal sweep`).

    One surface per (scenario, config), in the order they first appear. A cell is the mean of the
    metric over the seeds of that scenario (runs not done are left out, runs done with a NaN metric,
    i.e. no node localised, count as failed and are left out of the mean; a cell without a finite
    run is NaN). Other swept parameters (sigma_v, r_est, ...): `others="best"` takes per cell the
    combination with the lowest seed mean (its values are returned in `best_others`),
    `others="facet"` gives one surface per combination.

    Args:
        runs: `scenario`, `config` (R,) str, `seed` (R,) int, `param_<name>` (R,) swept values.
        metrics: name -> (R,) metric of every run. done: (R,) bool.
        metric: the metric to draw, one of `SWEEP_METRICS`. others: "best" or "facet".
        fixed: values of sigma_r [m] / tau used when one of them is not swept.
        method: filter name for the titles ("pgp", "parametric").

    Returns:
        Dicts for `write_report(sweeps=...)`: `sigma_r` (S,) [m], `tau` (T,), `rmse` (S, T) the
        metric (whatever `metric` is), `metric`, `label`, `title`, `n_runs`, `n_done`, `n_failed`
        (S, T) counts, `seeds`, `facet` {name: value}, `best_others` {name: (S, T) values}.
    """
    if metric not in SWEEP_METRICS:
        raise JaxcalError(f"sweep metric: one of {', '.join(SWEEP_METRICS)}; got {metric!r}")
    if others not in ("best", "facet"):
        raise JaxcalError(f"sweep others: best or facet; got {others!r}")
    if metric not in metrics:
        raise JaxcalError(f"sweep: no metric {metric!r} (has {', '.join(sorted(metrics))})")
    done = np.asarray(done, dtype=bool)
    n = done.size
    swept = [k[len("param_") :] for k in runs if k.startswith("param_")]
    if "sigma_r" not in swept and "tau" not in swept:
        raise JaxcalError(
            f"sweep: neither sigma_r nor tau is swept (swept: {', '.join(swept) or 'nothing'}); "
            "no sigma_r x tau surface to draw"
        )
    fixed = dict(fixed or {})
    sig, tau = _axis(runs, "sigma_r", fixed, n), _axis(runs, "tau", fixed, n)
    rest = [name for name in swept if name not in ("sigma_r", "tau")]
    combo = np.column_stack([np.asarray(runs[f"param_{k}"], np.float64) for k in rest] or [np.zeros(n)])
    _, combo_id = np.unique(combo, axis=0, return_inverse=True)
    combo_id = combo_id.reshape(-1)
    value = np.where(done, np.asarray(metrics[metric], dtype=np.float64), np.nan)
    scen = np.asarray(runs["scenario"]).astype(str)
    conf = np.asarray(runs.get("config", np.full(n, ""))).astype(str)
    seed = np.asarray(runs.get("seed", np.zeros(n, np.int64)))
    out = []
    for sc, cf in dict.fromkeys(zip(scen, conf, strict=True)):
        in_group = (scen == sc) & (conf == cf)
        facets = sorted(set(combo_id[in_group])) if others == "facet" and rest else [None]
        for fc in facets:
            sel = in_group if fc is None else in_group & (combo_id == fc)
            s_vals, t_vals = np.unique(sig[sel]), np.unique(tau[sel])
            c_vals = np.unique(combo_id[sel])
            si = np.searchsorted(s_vals, sig)
            ti = np.searchsorted(t_vals, tau)
            ci = np.searchsorted(c_vals, combo_id)
            shape = (s_vals.size, t_vals.size, c_vals.size)
            total, cnt, fin = np.zeros(shape), np.zeros(shape, np.int64), np.zeros(shape, np.int64)
            n_runs = np.zeros(shape[:2], np.int64)
            for r in np.flatnonzero(sel):
                idx = (si[r], ti[r], ci[r])
                n_runs[idx[:2]] += 1
                if done[r]:
                    cnt[idx] += 1
                    if np.isfinite(value[r]):
                        fin[idx] += 1
                        total[idx] += value[r]
            with np.errstate(invalid="ignore", divide="ignore"):
                mean = np.where(fin > 0, total / np.maximum(fin, 1), np.nan)
            pick = np.argmin(np.where(np.isfinite(mean), mean, np.inf), axis=2)  # best other combo
            surf = np.take_along_axis(mean, pick[..., None], axis=2)[..., 0]
            first_of = {c: np.flatnonzero(combo_id == c)[0] for c in c_vals}
            best_others = {}
            if rest and fc is None:
                for k, name in enumerate(rest):
                    vals = np.array([combo[first_of[c], k] for c in c_vals])
                    best_others[name] = np.where(np.isfinite(surf), vals[pick], np.nan)
            facet = {} if fc is None else {name: float(combo[first_of[fc], k]) for k, name in enumerate(rest)}
            seeds = sorted({int(x) for x in seed[sel]})
            where = sc + (f"/{cf}" if cf else "")
            extra = ", ".join(f"{k} {v:g}" for k, v in facet.items())
            title = f"{method + ': ' if method else ''}{where}" + (f" ({extra})" if extra else "")
            if len(seeds) > 1:
                title += f", mean of {len(seeds)} seeds"
            out.append(
                {
                    "sigma_r": s_vals,
                    "tau": t_vals,
                    "rmse": surf,
                    "metric": metric,
                    "label": SWEEP_METRICS[metric],
                    "title": title,
                    "scenario": sc,
                    "config": cf,
                    "seeds": seeds,
                    "facet": facet,
                    "n_runs": n_runs,
                    "n_done": cnt.sum(axis=2),
                    "n_failed": (cnt - fin).sum(axis=2),
                    "best_others": best_others,
                }
            )
    return out


def _config_name(result: Result, dataset) -> str:
    anchors = result.frame_anchors()
    if anchors is None:
        return result.frame
    if isinstance(dataset, MeshDataset):
        order = {nid: i for i, nid in enumerate(dataset.node_ids)}
        try:
            ds_idx = tuple(order[result.ids[a]] for a in anchors)
        except (KeyError, IndexError):
            return result.frame
        for name, idx in dataset.configs:
            if tuple(idx) == ds_idx:
                return name
    return result.frame


def group_label(result: Result, dataset) -> str:
    """`method/configuration` of a result, e.g. `pgp/conf1`, `gp/world`."""
    return f"{result.method}/{_config_name(result, dataset)}"


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "x"


def _frame(result: Result) -> tuple[int, int, int]:
    """The frame nodes (a0, a1, a2) of a mesh result (every mesh result has them)."""
    frame = result.frame_anchors()
    if frame is None:
        raise JaxcalError(f"result {result.name or result.method!r} has no mesh frame")
    return frame


def _truth(dataset: MeshDataset) -> np.ndarray:
    """The dataset's true node positions (`report` refuses a dataset without them)."""
    if dataset.truth is None:
        raise JaxcalError(f"{dataset.name}: the truth dataset has no ground truth")
    return dataset.truth


def _epoch_errors(result: Result, dataset: MeshDataset) -> np.ndarray:
    """(K, N) position error per epoch and node in the result's frame (NaN: no estimate); a0 NaN."""
    from jaxcal.metrics import truth_in_result_frame

    pos = {v: i for i, v in enumerate(dataset.node_ids)}
    truth = truth_in_result_frame(result, _truth(dataset)[[pos[v] for v in result.ids]])
    track = result.track_position if result.track_position is not None else result.position[None]
    e = np.linalg.norm(track - truth[None], axis=2)
    anchors = result.frame_anchors()
    if anchors is not None:
        e[:, anchors[0]] = np.nan
    return e


def _fmt(v: Any, digits: int = 2) -> str:
    if v is None:
        return "–"
    if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
        return f"{int(v):,}"
    v = float(v)
    if not math.isfinite(v):
        return "–"
    return f"{v:,.{digits}f}"


def _table(head: Sequence[str], rows: Sequence[Sequence[str]], cls: str = "") -> str:
    h = "".join(f"<th>{html.escape(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}"><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>'


class _Page:
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
        fname = f"{_slug(name)}.png"
        from jaxcal.io.atomic import atomic_path

        with atomic_path(self.out / fname) as tmp:  # an interrupted report leaves no torn PNG
            fig.savefig(tmp, dpi=self.dpi, format="png")
        self.figures.append(fname)
        self.parts.append(
            f'<figure><img src="{html.escape(fname)}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>"
        )


def _ranging_section(page: _Page, ds, numbers: dict) -> None:
    from jaxcal import plot
    from jaxcal.metrics import pairwise_rmse, qq_r2, ranging_errors, ranging_statistics

    groups = ranging_statistics(ds)
    numbers["ranging"] = groups
    page.h2("Ranging errors |range − true distance| (Table I)")
    rows = [[g] + [_fmt(groups[g][k], d) for k, _, d in TABLE_KEYS] for g in ("los", "nlos", "all")]
    page.raw(_table(["group"] + [lab for _, lab, _ in TABLE_KEYS], rows, "num"))
    page.p("1σ / 2σ / 3σ: quantiles of |error| at 68.27 / 95.45 / 99.73 %; variance with ddof 0.")
    err, los = ranging_errors(ds)
    page.figure(
        plot.ranging_histograms(err, los),
        "fig09_ranging_residuals",
        "Fig. 9: signed ranging residuals, LOS / NLOS / all (log count axis).",
    )
    qq = qq_r2(ds)
    numbers["qq"] = {"r2_qq": qq["r2_qq"], "r2": qq["r2"]}
    page.p(
        f"Q-Q R² = {_fmt(qq['r2_qq'], 4)}; per-measurement R² of measured against true distance = {_fmt(qq['r2'], 4)}."
    )
    page.figure(
        plot.qq_plot(qq["true_q"], qq["measured_q"], qq["r2_qq"], qq["r2"]),
        "fig11a_qq",
        f"Fig. 11a: Q-Q plot of measured against true distances, R² = {_fmt(qq['r2_qq'], 3)}.",
    )
    if isinstance(ds, MeshDataset):
        pr = pairwise_rmse(ds)
        numbers["pairwise_rmse_m"] = pr
        worst = np.dstack(np.unravel_index(np.argsort(np.nan_to_num(pr, nan=-1.0), axis=None)[::-1][:3], pr.shape))[0]
        text = ", ".join(
            f"{ds.node_ids[i]}→{ds.node_ids[j]} {pr[i, j]:.1f} m" for i, j in worst if np.isfinite(pr[i, j])
        )
        page.figure(
            plot.pairwise_rmse_matrix(pr, ds.node_ids),
            "fig11b_pairwise_rmse",
            f"Fig. 11b: pairwise ranging RMSE; largest: {text}.",
        )


def _mesh_section(
    page: _Page, ds: MeshDataset, groups: dict[str, Result], evals: dict[str, dict], numbers: dict
) -> None:
    from jaxcal import plot

    page.h2("Calibration results")
    rows = []
    for label, ev in evals.items():
        node_rmse = np.array([n["rmse_m"] for n in ev["nodes"]])
        node_avail = np.array([n["availability"] for n in ev["nodes"]])
        rows.append(
            [
                label,
                _fmt(ev["rmse_m"]),
                _fmt(ev["final_rmse_m"]),
                _fmt(ev["aligned_rmse_m"]),
                _fmt(np.nanmedian(node_rmse) if np.isfinite(node_rmse).any() else np.nan),
                _fmt(100 * np.nanmean(node_avail), 1),
            ]
        )
    page.raw(
        _table(
            [
                "method/config",
                "RMSE [m]",
                "final RMSE [m]",
                "aligned RMSE [m]",
                "median node RMSE [m]",
                "mean availability [%]",
            ],
            rows,
            "num",
        )
    )
    page.p(
        "RMSE over every (node, epoch) estimate except a0, in the result's frame; final: final "
        "positions; aligned: final positions after the best rigid motion (with reflection) onto "
        "the truth."
    )
    labels = list(evals)
    ids = ds.node_ids
    # (method, configuration) of each group, from the result (labels may be the user's own)
    mc = {lab: (r.method, _config_name(r, ds)) for lab, r in groups.items()}
    head = ["node"] + [f"{lab} RMSE [m]" for lab in labels]
    rows = [[nid] + [_fmt(evals[lab]["nodes"][i]["rmse_m"]) for lab in labels] for i, nid in enumerate(ids)]
    page.raw("<details><summary>per-node RMSE</summary>" + _table(head, rows, "num") + "</details>")

    # Fig. 10: availability, per method with configurations side by side
    tracked = {lab: r for lab, r in groups.items() if r.track_position is not None}
    if tracked:
        avail: dict[str, dict[str, np.ndarray]] = {}
        for lab in tracked:
            m, conf = mc[lab]
            avail.setdefault(m, {})[conf] = np.array([n["availability"] for n in evals[lab]["nodes"]])
        rows = [[nid] + [_fmt(100 * avail[m][c][i], 1) for m in avail for c in avail[m]] for i, nid in enumerate(ids)]
        page.h2("Availability (Fig. 10)")
        page.figure(
            plot.availability_bars(ids, avail),
            "fig10_availability",
            "Fig. 10: share of epochs with a position estimate per node and configuration.",
        )
        page.raw(
            "<details><summary>availability [%]</summary>"
            + _table(["node"] + [f"{m}/{c}" for m in avail for c in avail[m]], rows, "num")
            + "</details>"
        )

    # Fig. 12 / 13: per-node distributions per method, ECDFs of all groups
    page.h2("Position errors per node (Fig. 12, 13)")
    errors = {lab: _epoch_errors(r, ds) for lab, r in groups.items()}
    by_method: dict[str, dict[str, np.ndarray]] = {}
    origin: dict[str, int] = {}
    for lab, e in errors.items():
        m, conf = mc[lab]
        by_method.setdefault(m, {})[conf] = e
        origin[conf] = _frame(groups[lab])[0]
    for m, confs in by_method.items():
        page.figure(
            plot.node_error_distributions(ids, confs, title=f"{m}: per-node position error over epochs", origin=origin),
            f"fig12a_node_errors_{m}",
            f"Fig. 12a/13a ({m}): per-epoch position errors per node (boxes 25–75 %, "
            "whiskers 5–95 %, diamonds: node RMSE).",
        )
    ecdf_rmse = {lab: np.array([n["rmse_m"] for n in ev["nodes"]]) for lab, ev in evals.items()}
    for (
        lab,
        r,
    ) in groups.items():  # a0 has error 0 by construction: leave it out of the distribution
        a = r.frame_anchors()
        if a is not None:
            ecdf_rmse[lab] = np.delete(ecdf_rmse[lab], a[0])
    page.figure(
        plot.rmse_ecdfs(ecdf_rmse, "node RMSE [m]", "ECDF of node RMSE (a0 excluded)"),
        "fig12b_ecdf_node_rmse",
        "Fig. 12b/13b: ECDF of the per-node RMSE of every method and configuration.",
    )
    page.figure(
        plot.rmse_ecdfs(
            {k: v for k, v in errors.items()},
            "position error per epoch [m]",
            "ECDF of per-epoch position errors",
        ),
        "fig13b_ecdf_epoch_errors",
        "ECDF of the per-epoch position errors (every node and epoch except a0).",
    )

    # final positions per frame
    page.h2("Final positions")
    by_conf: dict[str, dict[str, Result]] = {}
    for lab, r in groups.items():
        by_conf.setdefault(mc[lab][1], {})[lab] = r
    from jaxcal.metrics import truth_in_result_frame

    pos = {v: i for i, v in enumerate(ds.node_ids)}
    for conf, rs in by_conf.items():
        first = next(iter(rs.values()))
        truth = truth_in_result_frame(first, _truth(ds)[[pos[v] for v in first.ids]])
        est = {lab: (r.position, r.covariance) for lab, r in rs.items()}
        page.figure(
            plot.positions_map(truth, first.ids, est, title=conf),
            f"positions_{conf}",
            f"Final positions in frame {conf} ({first.frame}) with 95 % ellipses from the result's "
            "covariance, over the truth (x).",
        )


def _posterior_section(
    page: _Page,
    ds: MeshDataset,
    groups: dict[str, Result],
    evals: dict[str, dict],
    spec: str | PosteriorSpec,
    numbers: dict,
) -> None:
    from jaxcal import plot
    from jaxcal.mesh.pgp import run_pgp
    from jaxcal.metrics import truth_in_result_frame

    if spec == "none":
        return
    method = spec.method if isinstance(spec, PosteriorSpec) else "pgp"
    cand = [(lab, r) for lab, r in groups.items() if r.method == method and r.frame_anchors() is not None]
    if not cand:
        if isinstance(spec, PosteriorSpec):
            raise JaxcalError(f"--posteriors: no {method} result among the inputs")
        return
    lab, res = cand[0]
    a0, a1, a2 = _frame(res)
    ids = list(res.ids)
    if isinstance(spec, PosteriorSpec):
        unknown = [n for n in spec.nodes if n not in ids]
        if unknown:
            raise JaxcalError(f"--posteriors: unknown node(s) {', '.join(unknown)} (known: {', '.join(ids)})")
        nodes = list(spec.nodes)
        epochs = sorted(set(spec.epochs))
        if epochs[-1] >= ds.n_epochs:
            raise JaxcalError(f"--posteriors: epoch {epochs[-1]} beyond the dataset's {ds.n_epochs} epochs")
    else:
        epochs = [e for e in AUTO_POSTERIOR_EPOCHS if e < ds.n_epochs] or [ds.n_epochs - 1]
        fe = np.array([n["final_error_m"] for n in evals[lab]["nodes"]])
        others = [i for i in range(len(ids)) if i not in (a0, a1, a2) and np.isfinite(fe[i])]
        pick = [a2]
        if others:
            pick += [min(others, key=lambda i: fe[i]), max(others, key=lambda i: fe[i])]
        nodes = [ids[i] for i in dict.fromkeys(pick)]
    pos = {v: i for i, v in enumerate(ds.node_ids)}
    frame_ds = (pos[ids[a0]], pos[ids[a1]], pos[ids[a2]])
    k = epochs[-1] + 1
    short = dataclasses.replace(
        ds,
        time=ds.time[:k],
        range=ds.range[:k],
        fp_rssi=None if ds.fp_rssi is None else ds.fp_rssi[:k],
        rx_rssi=None if ds.rx_rssi is None else ds.rx_rssi[:k],
        configs=(("report", frame_ds),),
    )
    params = dict(res.params) if res.params else None
    note = ""
    try:
        _, info = run_pgp(short, params, "report", mode=res.method, snapshot_epochs=epochs)
    except JaxcalError as e:  # parameters of another version: the defaults still show the filter's behaviour
        _, info = run_pgp(short, None, "report", mode=res.method, snapshot_epochs=epochs)
        note = f" (the result's parameters were not accepted: {e}; default parameters used)"
    rows = [pos[n] for n in nodes]
    grids = info.snapshots[:, rows]
    truth = truth_in_result_frame(res, _truth(ds)[[pos[v] for v in ids]])[[ids.index(n) for n in nodes]]
    numbers["posteriors"] = {
        "result": lab,
        "nodes": nodes,
        "epochs": list(map(int, info.snapshot_epochs)),
    }
    page.h2("Posterior grids (Fig. 6 style)")
    est = info.raw_track[info.snapshot_epochs][:, rows]
    page.figure(
        plot.posterior_grids(info.axis_m, grids, nodes, info.snapshot_epochs, truth, est),
        f"fig06_posteriors_{_slug(lab)}",
        f"Posterior grids of {', '.join(nodes)} at epochs "
        f"{', '.join(map(str, info.snapshot_epochs))} "
        f"({lab}, re-run on the first {k} epochs){note}.",
    )


def _trajectory_section(
    page: _Page,
    ds: TrajectoryDataset,
    groups: dict[str, Result],
    evals: dict[str, dict],
    numbers: dict,
) -> None:
    from jaxcal import plot
    from jaxcal.metrics import truth_in_result_frame

    page.h2("Anchor calibration")
    labels = list(evals)
    rows = [[lab, _fmt(evals[lab]["mean_error_m"])] for lab in labels]
    page.raw(_table(["method/frame", "mean anchor error [m]"], rows, "num"))
    first = next(iter(groups.values()))
    head = ["anchor"] + [f"{lab} error [m]" for lab in labels]
    rows = [[a] + [_fmt(evals[lab]["anchors"][i]["error_m"]) for lab in labels] for i, a in enumerate(first.ids)]
    page.raw(_table(head, rows, "num"))
    truth = None
    if ds.anchor_truth is not None:
        pos = {v: i for i, v in enumerate(ds.anchor_ids)}
        truth = truth_in_result_frame(first, ds.anchor_truth[[pos[v] for v in first.ids]])
    est = {lab: (r.position, r.covariance) for lab, r in groups.items()}
    page.figure(
        plot.trajectory_anchors(ds.pose_position, truth, first.ids, est),
        "anchors_trajectory",
        "Estimated anchors (±2σ from the result's covariance) over the platform path and the surveyed anchors.",
    )
    errs = {lab: np.array([a["error_m"] for a in ev["anchors"]]) for lab, ev in evals.items()}
    page.figure(
        plot.rmse_ecdfs(errs, "anchor error [m]", "ECDF of anchor errors", log_x=False),
        "ecdf_anchor_errors",
        "ECDF of the anchor errors per method.",
    )


def _sweep_cell(sw: Mapping[str, Any], r: np.ndarray, others: dict, a: int, b: int) -> str:
    """Table text of cell (a, b): value, the best other parameters, runs not done or failed."""
    txt = _fmt(r[a, b], 3)
    if others:
        txt += " (" + ", ".join(f"{k} {v[a, b]:g}" for k, v in others.items()) + ")"
    if "n_done" in sw and "n_runs" in sw and sw["n_done"][a][b] < sw["n_runs"][a][b]:
        txt += f" [{sw['n_done'][a][b]}/{sw['n_runs'][a][b]} done]"
    if "n_failed" in sw and sw["n_failed"][a][b]:
        txt += f" [{sw['n_failed'][a][b]} failed]"
    return txt


def _sweep_section(page: _Page, sweeps: Sequence[Mapping[str, Any]], numbers: dict) -> None:
    from jaxcal import plot

    page.h2("Parameter sweeps: sigma_r × tau")
    numbers["sweeps"] = []
    for i, sw in enumerate(sweeps):
        r = np.asarray(sw["rmse"], dtype=np.float64)
        s = np.asarray(sw["sigma_r"], dtype=np.float64)
        t = np.asarray(sw["tau"], dtype=np.float64)
        if r.shape != (s.size, t.size):
            raise JaxcalError(f"sweep {i}: rmse shape {r.shape} is not (sigma_r, tau) = ({s.size}, {t.size})")
        metric = sw.get("metric", "rmse_m")
        label = sw.get("label", SWEEP_METRICS.get(metric, metric))
        name = sw.get("title", "")
        best = np.unravel_index(np.nanargmin(r), r.shape) if np.isfinite(r).any() else None
        others = {k: np.asarray(v, np.float64) for k, v in (sw.get("best_others") or {}).items()}
        entry: dict[str, Any] = {
            "title": name,
            "metric": metric,
            "sigma_r_m": s,
            "tau": t,
            "values": r,
            "best": None
            if best is None
            else {
                "sigma_r_m": float(s[best[0]]),
                "tau": float(t[best[1]]),
                metric: float(r[best]),
                **{k: float(v[best]) for k, v in others.items()},
            },
        }
        for key in ("scenario", "config", "seeds", "facet", "n_runs", "n_done", "n_failed"):
            if key in sw:
                entry[key] = sw[key]
        if others:
            entry["best_others"] = others
        numbers["sweeps"].append(entry)
        page.raw(f"<h3>{html.escape(name or f'sweep {i}')}</h3>")
        page.figure(
            plot.sweep_surface(s, t, r, name, label=label),
            f"sweep_{i}",
            f"{label} over sigma_r × tau{': ' + name if name else ''} (star: lowest).",
        )

        rows = [[f"{s[a]:g}"] + [_sweep_cell(sw, r, others, a, b) for b in range(t.size)] for a in range(s.size)]
        page.raw(_table(["sigma_r [m] ↓ tau →"] + [f"{v:g}" for v in t], rows, "num"))
        notes = []
        if best is not None:
            notes.append(f"lowest {label}: {r[best]:.3f} at sigma_r {s[best[0]]:g} m, tau {t[best[1]]:g}")
        if "seeds" in sw and len(sw["seeds"]) > 1:
            notes.append(f"cells are the mean over seeds {', '.join(map(str, sw['seeds']))}")
        if others:
            notes.append(
                f"other swept parameters ({', '.join(others)}): per cell the value with the lowest mean, in brackets"
            )
        if "n_failed" in sw and np.sum(sw["n_failed"]):
            notes.append("failed runs (no node localised) are left out of the means")
        if notes:
            page.p("; ".join(notes) + ".")


_CSS = """body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;
color:#222}table{border-collapse:collapse;margin:.6em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em}
table.num td{text-align:right}table.num td:first-child{text-align:left}th{background:#f0f0f0}
figure{margin:1.2em 0}img{max-width:100%;border:1px solid #eee}figcaption{font-size:.9em;color:#555}
details{margin:.5em 0}"""


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
    page = _Page(out, dpi)
    numbers: dict[str, Any] = {"dataset": None if ds is None else ds.name, "groups": {}}
    done = progress or (lambda k: None)
    if ds is not None:
        _ranging_section(page, ds, numbers)
        done(1)
    if groups:
        if isinstance(ds, MeshDataset):
            _mesh_section(page, ds, groups, evals, numbers)
            done(1)
            _posterior_section(page, ds, groups, evals, posteriors, numbers)
            done(1)
        elif isinstance(ds, TrajectoryDataset):
            _trajectory_section(page, ds, groups, evals, numbers)
            done(1)
    for lab, ev in evals.items():
        numbers["groups"][lab] = {k: v for k, v in ev.items() if k != "ecdf"}
    if sweeps:
        _sweep_section(page, sweeps, numbers)
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
        f"<style>{_CSS}</style></head><body><h1>{html.escape(head)}</h1><p>{html.escape(meta)}</p>"
        + "\n".join(page.parts)
        + "</body></html>\n"
    )
    from jaxcal.io.atomic import atomic_write_text

    atomic_write_text(out / "report.json", json.dumps(json_safe(numbers), indent=1, allow_nan=False))
    index = out / "index.html"
    atomic_write_text(index, doc)
    return index
