"""The dataset and result sections of `jaxcal.report`: ranging errors (Table I, Fig. 9, 11), mesh results
(summary, Fig. 10, 12, 13, final positions), PGP posterior grids (Fig. 6 style, re-run) and trajectory
anchors. Each section adds its figures and tables to a `jaxcal.report_page.Page` and its numbers to
the report's JSON."""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxcal.data import MeshDataset, Result, TrajectoryDataset
from jaxcal.errors import JaxcalError
from jaxcal.report_page import Page, fmt, slug, table

__all__ = [
    "AUTO_POSTERIOR_EPOCHS",
    "PosteriorSpec",
    "group_label",
    "mesh_section",
    "parse_posteriors",
    "posterior_section",
    "ranging_section",
    "trajectory_section",
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


def ranging_section(page: Page, ds, numbers: dict) -> None:
    from jaxcal import plot
    from jaxcal.metrics import pairwise_rmse, qq_r2, ranging_errors, ranging_statistics

    groups = ranging_statistics(ds)
    numbers["ranging"] = groups
    page.h2("Ranging errors |range − true distance| (Table I)")
    rows = [[g] + [fmt(groups[g][k], d) for k, _, d in TABLE_KEYS] for g in ("los", "nlos", "all")]
    page.raw(table(["group"] + [lab for _, lab, _ in TABLE_KEYS], rows, "num"))
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
        f"Q-Q R² = {fmt(qq['r2_qq'], 4)}; per-measurement R² of measured against true distance = {fmt(qq['r2'], 4)}."
    )
    page.figure(
        plot.qq_plot(qq["true_q"], qq["measured_q"], qq["r2_qq"], qq["r2"]),
        "fig11a_qq",
        f"Fig. 11a: Q-Q plot of measured against true distances, R² = {fmt(qq['r2_qq'], 3)}.",
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


def mesh_section(page: Page, ds: MeshDataset, groups: dict[str, Result], evals: dict[str, dict], numbers: dict) -> None:
    from jaxcal import plot

    page.h2("Calibration results")
    rows = []
    for label, ev in evals.items():
        node_rmse = np.array([n["rmse_m"] for n in ev["nodes"]])
        node_avail = np.array([n["availability"] for n in ev["nodes"]])
        rows.append(
            [
                label,
                fmt(ev["rmse_m"]),
                fmt(ev["final_rmse_m"]),
                fmt(ev["aligned_rmse_m"]),
                fmt(np.nanmedian(node_rmse) if np.isfinite(node_rmse).any() else np.nan),
                fmt(100 * np.nanmean(node_avail), 1),
            ]
        )
    page.raw(
        table(
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
    rows = [[nid] + [fmt(evals[lab]["nodes"][i]["rmse_m"]) for lab in labels] for i, nid in enumerate(ids)]
    page.raw("<details><summary>per-node RMSE</summary>" + table(head, rows, "num") + "</details>")

    # Fig. 10: availability, per method with configurations side by side
    tracked = {lab: r for lab, r in groups.items() if r.track_position is not None}
    if tracked:
        avail: dict[str, dict[str, np.ndarray]] = {}
        for lab in tracked:
            m, conf = mc[lab]
            avail.setdefault(m, {})[conf] = np.array([n["availability"] for n in evals[lab]["nodes"]])
        rows = [[nid] + [fmt(100 * avail[m][c][i], 1) for m in avail for c in avail[m]] for i, nid in enumerate(ids)]
        page.h2("Availability (Fig. 10)")
        page.figure(
            plot.availability_bars(ids, avail),
            "fig10_availability",
            "Fig. 10: share of epochs with a position estimate per node and configuration.",
        )
        page.raw(
            "<details><summary>availability [%]</summary>"
            + table(["node"] + [f"{m}/{c}" for m in avail for c in avail[m]], rows, "num")
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


def posterior_section(
    page: Page,
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
        f"fig06_posteriors_{slug(lab)}",
        f"Posterior grids of {', '.join(nodes)} at epochs "
        f"{', '.join(map(str, info.snapshot_epochs))} "
        f"({lab}, re-run on the first {k} epochs){note}.",
    )


def trajectory_section(
    page: Page,
    ds: TrajectoryDataset,
    groups: dict[str, Result],
    evals: dict[str, dict],
    numbers: dict,
) -> None:
    from jaxcal import plot
    from jaxcal.metrics import truth_in_result_frame

    page.h2("Anchor calibration")
    labels = list(evals)
    rows = [[lab, fmt(evals[lab]["mean_error_m"])] for lab in labels]
    page.raw(table(["method/frame", "mean anchor error [m]"], rows, "num"))
    first = next(iter(groups.values()))
    head = ["anchor"] + [f"{lab} error [m]" for lab in labels]
    rows = [[a] + [fmt(evals[lab]["anchors"][i]["error_m"]) for lab in labels] for i, a in enumerate(first.ids)]
    page.raw(table(head, rows, "num"))
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
