"""Evaluation: ranging statistics (Table I, Fig. 11) and calibration errors (Figs. 10, 12, 13).

Pure functions of datasets and results (NumPy; they run once per evaluation, outside traced code).

Ranging errors are `range - true distance` per measurement. For a mesh file, every finite off-diagonal
`range[k, i, j]` is one measurement, except that a mirrored copy (`range[k, j, i]` exactly equal to
`range[k, i, j]`, as in files that store one measurement per pair in a symmetric matrix) is counted once.
For a trajectory file the true distance is from the anchor to the tag antenna, with the pose interpolated
linearly in position and normalised-linearly in orientation at the range time.

Calibration errors follow CONTRACT section 2 (`jaxcal evaluate`): errors in the result's frame with the
truth transformed into it (`to_frame` of the result's `frame_anchors()`, in 3-D when the truth is 3-D,
then the first two axes for a 2-D estimate).
"""

from __future__ import annotations

import numpy as np

from jaxcal.data import MeshDataset, Result, TrajectoryDataset, mesh_true_distances
from jaxcal.errors import JaxcalError
from jaxcal.mesh.frame import align_rigid, apply_rigid, to_frame

__all__ = [
    "SIGMA_LEVELS",
    "error_statistics",
    "ranging_errors",
    "ranging_statistics",
    "pairwise_rmse",
    "qq_r2",
    "ecdf",
    "truth_in_result_frame",
    "evaluate_mesh",
    "covariance_consistency",
    "evaluate_trajectory",
    "evaluate",
    "place_success",
]

# Probability mass within 1, 2, 3 standard deviations of a Gaussian: Table I's "1 sigma" ... quantiles.
SIGMA_LEVELS = (0.6827, 0.9545, 0.9973)


def error_statistics(abs_err: np.ndarray) -> dict:
    """Table I statistics of absolute ranging errors.

    Args:
        abs_err: (M,) |range - true distance| [m]; NaN entries are ignored.

    Returns:
        dict with `count`, `mean_m`, `median_m`, `variance_m2` (population variance, ddof 0),
        `q1sigma_m`, `q2sigma_m`, `q3sigma_m` (quantiles at 68.27 / 95.45 / 99.73 %, linear
        interpolation), `p25_m`, `p50_m`, `p75_m`; NaN values when there is no error.
    """
    x = np.asarray(abs_err, dtype=np.float64).ravel()
    x = x[np.isfinite(x)]
    keys = (
        "mean_m",
        "median_m",
        "variance_m2",
        "q1sigma_m",
        "q2sigma_m",
        "q3sigma_m",
        "p25_m",
        "p50_m",
        "p75_m",
    )
    if x.size == 0:
        return {"count": 0, **{k: float("nan") for k in keys}}
    q = np.quantile(x, [*SIGMA_LEVELS, 0.25, 0.5, 0.75])
    return {
        "count": int(x.size),
        "mean_m": float(x.mean()),
        "median_m": float(np.median(x)),
        "variance_m2": float(x.var()),
        "q1sigma_m": float(q[0]),
        "q2sigma_m": float(q[1]),
        "q3sigma_m": float(q[2]),
        "p25_m": float(q[3]),
        "p50_m": float(q[4]),
        "p75_m": float(q[5]),
    }


def _quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (M, 3) by unit quaternions q (M, 4), scalar last."""
    u, w = q[:, :3], q[:, 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _trajectory_true_distances(ds: TrajectoryDataset) -> np.ndarray:
    if ds.anchor_truth is None:
        raise JaxcalError(f"{ds.name}: no anchor truth, cannot compute ranging errors")
    t = ds.range_time
    pos = np.column_stack([np.interp(t, ds.pose_time, ds.pose_position[:, c]) for c in range(3)])
    outside = (t < ds.pose_time[0]) | (t > ds.pose_time[-1])
    lever = ds.lever_arm[ds.range_tag]
    if ds.pose_orientation is not None:
        qs = ds.pose_orientation.copy()
        # neighbouring quaternions on the same hemisphere so that linear interpolation is meaningful
        for i in range(1, qs.shape[0]):
            if qs[i] @ qs[i - 1] < 0:
                qs[i] = -qs[i]
        q = np.column_stack([np.interp(t, ds.pose_time, qs[:, c]) for c in range(4)])
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        lever = _quat_rotate(q, lever)
    tag = pos + lever
    d = np.linalg.norm(ds.anchor_truth[ds.range_anchor] - tag, axis=1)
    d[outside] = np.nan
    return d


def ranging_errors(dataset: MeshDataset | TrajectoryDataset) -> tuple[np.ndarray, np.ndarray]:
    """Signed ranging errors and their LOS labels, one entry per measurement.

    Args:
        dataset: a mesh or trajectory dataset with truth.

    Returns:
        (err, los): err (M,) `range - true distance` [m]; los (M,) int8 (1 LOS, 0 NLOS, -1 unknown).
    """
    if isinstance(dataset, MeshDataset):
        if dataset.truth is None:
            raise JaxcalError(f"{dataset.name}: no node truth, cannot compute ranging errors")
        r = dataset.range.astype(np.float64)
        n = dataset.n_nodes
        err = r - mesh_true_distances(dataset.truth)[None]
        keep = np.isfinite(err)
        keep[:, np.arange(n), np.arange(n)] = False
        lower = np.tril(np.ones((n, n), dtype=bool), -1)
        mirrored = lower[None] & (dataset.range == np.swapaxes(dataset.range, 1, 2))
        keep &= ~mirrored
        los = np.full((n, n), -1, np.int8) if dataset.los is None else dataset.los
        los_k = np.broadcast_to(los, err.shape)
        return err[keep], los_k[keep].astype(np.int8)
    d = _trajectory_true_distances(dataset)
    err = dataset.range.astype(np.float64) - d
    keep = np.isfinite(err)
    los = dataset.range_los if dataset.range_los is not None else np.full(err.shape, -1, np.int8)
    return err[keep], los[keep].astype(np.int8)


def ranging_statistics(dataset: MeshDataset | TrajectoryDataset) -> dict:
    """Table I: statistics of |range - true distance| by group (CONTRACT 2, `jaxcal stats`).

    Returns:
        {"los": {...}, "nlos": {...}, "all": {...}}, each `error_statistics` plus `share` (the group's
        fraction of all measurements; NaN for los/nlos when no measurement has a LOS label).
    """
    err, los = ranging_errors(dataset)
    a = np.abs(err)
    total = a.size
    labelled = bool(np.any(los >= 0))
    out = {}
    for name, mask in (("los", los == 1), ("nlos", los == 0), ("all", np.ones(total, bool))):
        s = error_statistics(a[mask])
        if name == "all":
            share = 1.0 if total else float("nan")
        else:
            share = float(mask.sum() / total) if (total and labelled) else float("nan")
        out[name] = {"share": share, **s}
    return out


def pairwise_rmse(dataset: MeshDataset) -> np.ndarray:
    """(N, N) RMSE [m] of range i->j over the epochs where it was measured (Fig. 11b); NaN if never."""
    if dataset.truth is None:
        raise JaxcalError(f"{dataset.name}: no node truth, cannot compute ranging errors")
    err = dataset.range.astype(np.float64) - mesh_true_distances(dataset.truth)[None]
    cnt = np.isfinite(err).sum(axis=0)
    ss = np.nansum(err * err, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, np.sqrt(ss / np.maximum(cnt, 1)), np.nan)


def qq_r2(dataset: MeshDataset | TrajectoryDataset, n_quantiles: int = 101) -> dict:
    """Measured against true distances (Fig. 11a).

    Returns:
        dict with `r2_qq` (coefficient of determination of the straight-line fit of the sorted measured
        distances against the sorted true distances, i.e. of the Q-Q plot), `r2` (squared correlation
        of measured and true distance per measurement), and `true_q`, `measured_q` ((n_quantiles,)
        quantiles at evenly spaced probabilities, for plotting).
    """
    err, _ = ranging_errors(dataset)
    if isinstance(dataset, MeshDataset):
        assert dataset.truth is not None  # ranging_errors refuses a dataset without truth
        d = mesh_true_distances(dataset.truth)
        n = dataset.n_nodes
        r = dataset.range.astype(np.float64)
        keep = np.isfinite(r - d[None])
        keep[:, np.arange(n), np.arange(n)] = False
        lower = np.tril(np.ones((n, n), dtype=bool), -1)
        keep &= ~(lower[None] & (dataset.range == np.swapaxes(dataset.range, 1, 2)))
        true = np.broadcast_to(d, r.shape)[keep]
        meas = r[keep]
    else:
        true_all = _trajectory_true_distances(dataset)
        keep = np.isfinite(true_all) & np.isfinite(dataset.range)
        true, meas = true_all[keep], dataset.range.astype(np.float64)[keep]
    assert true.size == err.size
    if true.size < 2:
        return {
            "r2_qq": float("nan"),
            "r2": float("nan"),
            "true_q": np.array([]),
            "measured_q": np.array([]),
        }

    def r2_of(x, y):
        sx, sy = x.std(), y.std()
        if sx == 0 or sy == 0:
            return float("nan")
        return float(np.corrcoef(x, y)[0, 1] ** 2)

    ts, ms = np.sort(true), np.sort(meas)
    p = np.linspace(0.0, 1.0, n_quantiles)
    return {
        "r2_qq": r2_of(ts, ms),
        "r2": r2_of(true, meas),
        "true_q": np.quantile(true, p),
        "measured_q": np.quantile(meas, p),
    }


def ecdf(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Empirical CDF of the finite values: (sorted x, P(X <= x)), both (M,)."""
    x = np.sort(np.asarray(values, dtype=np.float64).ravel())
    x = x[np.isfinite(x)]
    return x, np.arange(1, x.size + 1, dtype=np.float64) / max(x.size, 1)


def _match_order(ids_result, ids_truth, what: str) -> np.ndarray:
    pos = {v: i for i, v in enumerate(ids_truth)}
    missing = [v for v in ids_result if v not in pos]
    if missing:
        raise JaxcalError(f"result ids not in the truth's {what}: {', '.join(missing[:5])}")
    return np.array([pos[v] for v in ids_result], dtype=np.int64)


def truth_in_result_frame(result: Result, truth: np.ndarray) -> np.ndarray:
    """Truth (N, Dt) expressed in the result's frame, with the result's dimension D.

    For a mesh frame `anchors:i0,i1,i2` the truth is moved into that frame (in 3-D when it is 3-D) and
    then cut to the first D axes; for `world` it is only cut. Rows follow the result's ids.
    """
    d = result.position.shape[1]
    t = np.asarray(truth, dtype=np.float64)
    anchors = result.frame_anchors()
    if anchors is not None:
        a0, a1, a2 = anchors
        n = t.shape[0]
        if max(anchors) >= n or not np.isfinite(t[list(anchors)]).all():
            raise JaxcalError(f"frame anchors {anchors} have no truth; cannot evaluate in the result's frame")
        try:
            t = to_frame(t, a0, a1, a2)
        except ValueError as e:
            raise JaxcalError(f"truth: {e}") from None
    if t.shape[1] >= d:
        return t[:, :d]
    return np.column_stack([t, np.zeros((t.shape[0], d - t.shape[1]))])


def evaluate_mesh(result: Result, dataset: MeshDataset) -> dict:
    """Errors of a mesh result against the dataset's truth (CONTRACT 2, `jaxcal evaluate`).

    Args:
        result: (N, D) final positions and optionally a (K, N, D) track, in the frame `result.frame`.
        dataset: the mesh dataset with `truth` (N, Dt).

    Returns:
        dict: `method`, `dataset`, `rmse_m` (over every finite (node, epoch) estimate except a0; over
        the final positions when there is no track), `final_rmse_m` (final positions, a0 excluded),
        `aligned_rmse_m` (final positions after the best rigid motion with reflection, all nodes),
        `nodes` [{id, rmse_m, final_error_m, availability}], and `ecdf` (per-epoch errors and per-node
        RMSE as (x, p) pairs, for Fig. 12b).
    """
    if dataset.truth is None:
        raise JaxcalError(f"{dataset.name}: no truth to evaluate against")
    # evaluation happens in the result's node order; its frame indices refer to that order too
    order = _match_order(result.ids, dataset.node_ids, "node ids")
    truth = truth_in_result_frame(result, dataset.truth[order])
    anchors = result.frame_anchors()
    a0 = anchors[0] if anchors is not None else -1
    n = len(result.ids)
    not_a0 = np.arange(n) != a0

    final_err = np.linalg.norm(result.position - truth, axis=1)
    if result.track_position is not None and result.track_position.shape[0] > 0:
        track = result.track_position
        has = np.isfinite(track).all(axis=2)
        e = np.linalg.norm(track - truth[None], axis=2)
        e = np.where(has, e, np.nan)
        availability = has.mean(axis=0)
    else:
        has = np.isfinite(result.position).all(axis=1)[None]
        e = np.where(has, final_err[None], np.nan)
        availability = has[0].astype(np.float64)
    e = np.where(np.isfinite(truth).all(axis=1)[None], e, np.nan)

    def rms(x):
        x = x[np.isfinite(x)]
        return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")

    node_rmse = np.array([rms(e[:, i]) for i in range(n)])
    r, t = align_rigid(result.position, truth, reflection=True)
    aligned = np.linalg.norm(apply_rigid(result.position, r, t) - truth, axis=1)
    return {
        "method": result.method,
        "dataset": result.dataset or dataset.name,
        "rmse_m": rms(e[:, not_a0]),
        "final_rmse_m": rms(final_err[not_a0]),
        "aligned_rmse_m": rms(aligned),
        "nodes": [
            {
                "id": nid,
                "rmse_m": float(node_rmse[i]),
                "final_error_m": float(final_err[i]),
                "availability": float(availability[i]),
            }
            for i, nid in enumerate(result.ids)
        ],
        "ecdf": {"epoch_error": ecdf(e[:, not_a0]), "node_rmse": ecdf(node_rmse[not_a0])},
    }


def covariance_consistency(result: Result, dataset: MeshDataset | TrajectoryDataset) -> dict | None:
    """How well a result's covariance predicts its actual errors (None without a covariance or truth).

    Mesh: errors are taken in the result's frame (truth transformed into it; for 3-D, the truth or its
    mirror image through the x-y plane, whichever is nearer), over the final positions of every node except
    a0. Trajectory: anchor errors in the world frame. Rows need a finite covariance block and truth; NaN
    coordinates (an axis the data cannot observe) and coordinates the frame fixes (variance <= 1e-12 m^2,
    e.g. a1's y) are left out of the normalised errors.

    Returns:
        dict: `nodes` (rows used), `error_rmse_m` (RMS of |error|), `predicted_rmse_m` (sqrt of the mean
        covariance trace, what that RMS should be), `nees_per_dof` (sum of e^T C^-1 e over the sum of free
        coordinates: 1 for a covariance that is right, > 1 when it is too small), `coverage95` (share of
        rows whose truth is inside the 95 % ellipse / ellipsoid), and for 3-D results the same RMS and NEES
        for the horizontal (x, y) and vertical (z) parts: `h_error_rmse_m`, `h_predicted_rmse_m`,
        `h_nees_per_dof`, `h_coverage95` (the 95 % ellipse of the horizontal block alone), `v_error_rmse_m`,
        `v_predicted_rmse_m`, `v_nees_per_dof`, `v_coverage95`.
    """
    from scipy.stats import chi2

    if result.covariance is None:
        return None
    if isinstance(dataset, MeshDataset):
        if dataset.truth is None:
            return None
        order = _match_order(result.ids, dataset.node_ids, "node ids")
        truth = truth_in_result_frame(result, dataset.truth[order])
        if truth.shape[1] == 3:  # ranges cannot tell a 3-D scene from its mirror image: take the nearer one
            mirror = truth * np.array([1.0, 1.0, -1.0])
            if np.nansum((result.position - mirror) ** 2) < np.nansum((result.position - truth) ** 2):
                truth = mirror
        anchors = result.frame_anchors()
        a0 = anchors[0] if anchors is not None else -1
    else:
        if dataset.anchor_truth is None:
            return None
        order = _match_order(result.ids, dataset.anchor_ids, "anchor ids")
        truth = truth_in_result_frame(result, dataset.anchor_truth[order])
        a0 = -1
    d = result.position.shape[1]
    parts = {"": np.arange(d)}
    if d == 3:
        parts.update({"h_": np.arange(2), "v_": np.array([2])})
    sq: dict[str, list[float]] = {k: [] for k in parts}  # squared errors, per node
    tr: dict[str, list[float]] = {k: [] for k in parts}  # predicted squared errors (covariance traces)
    nees: dict[str, float] = dict.fromkeys(parts, 0.0)
    dof: dict[str, int] = dict.fromkeys(parts, 0)
    inside: dict[str, list[bool]] = {k: [] for k in parts}
    for k in range(len(result.ids)):
        e_all, c_all = result.position[k] - truth[k], np.asarray(result.covariance[k], dtype=np.float64)
        if k == a0 or not np.isfinite(truth[k]).all():
            continue
        for name, axes in parts.items():
            e, c = e_all[axes], c_all[np.ix_(axes, axes)]
            use = np.isfinite(e) & np.isfinite(np.diag(c))
            if not use.any():
                continue
            e, c = e[use], c[np.ix_(use, use)]
            if not np.isfinite(c).all():
                continue
            free = np.diag(c) > 1e-12
            sq[name].append(float(e @ e))
            tr[name].append(float(np.trace(c)))
            if free.any():
                q = float(e[free] @ np.linalg.lstsq(c[np.ix_(free, free)], e[free], rcond=None)[0])
                nees[name] += q
                dof[name] += int(free.sum())
                inside[name].append(q <= chi2.ppf(0.95, int(free.sum())))
    if not sq[""]:
        return None
    out: dict[str, float] = {"nodes": len(sq[""])}
    for name in parts:
        if not sq[name]:
            continue
        out[f"{name}error_rmse_m"] = float(np.sqrt(np.mean(sq[name])))
        out[f"{name}predicted_rmse_m"] = float(np.sqrt(np.mean(tr[name])))
        out[f"{name}nees_per_dof"] = nees[name] / dof[name] if dof[name] else float("nan")
        out[f"{name}coverage95"] = float(np.mean(inside[name])) if inside[name] else float("nan")
    return out


def predicted_uncertainty(result: Result) -> dict:
    """What a result says about its own accuracy, without truth (for `calibrate`'s closing line).

    Returns:
        dict: `fixed` (rows with every coordinate estimated), `partial` (rows with some coordinate NaN,
        e.g. a height the path cannot observe), `total`, and `predicted_rmse_m`: sqrt of the mean trace of
        the finite covariance blocks over the estimated rows (NaN without a covariance).
    """
    pos = np.asarray(result.position, dtype=np.float64)
    fin = np.isfinite(pos)
    fixed = fin.all(axis=1)
    partial = fin.any(axis=1) & ~fixed
    traces = []
    if result.covariance is not None:
        for k in np.flatnonzero(fin.any(axis=1)):
            c = np.asarray(result.covariance[k], dtype=np.float64)
            d = np.diag(c)[fin[k]]
            if np.isfinite(d).all():
                traces.append(float(d.sum()))
    return {
        "fixed": int(fixed.sum()),
        "partial": int(partial.sum()),
        "total": int(pos.shape[0]),
        "predicted_rmse_m": float(np.sqrt(np.mean(traces))) if traces else float("nan"),
    }


def evaluate_trajectory(result: Result, dataset: TrajectoryDataset) -> dict:
    """Anchor errors of a trajectory result (CONTRACT 2): `method`, `dataset`, `mean_error_m`,
    `anchors` [{id, error_m}] (Euclidean error over the result's D axes; over the estimated ones where an
    axis the path cannot observe is NaN; NaN without estimate),
    and `ecdf` of the anchor errors."""
    if dataset.anchor_truth is None:
        raise JaxcalError(f"{dataset.name}: no anchor truth to evaluate against")
    order = _match_order(result.ids, dataset.anchor_ids, "anchor ids")
    truth = truth_in_result_frame(result, dataset.anchor_truth[order])
    diff = result.position - truth
    has = np.isfinite(result.position).any(axis=1)  # a NaN height (unobservable axis): the axes estimated
    err = np.where(has, np.sqrt(np.nansum(diff**2, axis=1)), np.nan)
    fin = err[np.isfinite(err)]
    return {
        "method": result.method,
        "dataset": result.dataset or dataset.name,
        "mean_error_m": float(fin.mean()) if fin.size else float("nan"),
        "anchors": [{"id": a, "error_m": float(err[i])} for i, a in enumerate(result.ids)],
        "ecdf": {"anchor_error": ecdf(err)},
    }


def evaluate(result: Result, dataset: MeshDataset | TrajectoryDataset) -> dict:
    """`evaluate_mesh` or `evaluate_trajectory` according to the dataset's kind."""
    if isinstance(dataset, MeshDataset):
        return evaluate_mesh(result, dataset)
    return evaluate_trajectory(result, dataset)


PLACE_SUCCESS_RADIUS_M = 8.5  # the match criterion of the place-recognition paper (Section IV-E)


def place_success(best: np.ndarray, truth: np.ndarray, radius_m: float = PLACE_SUCCESS_RADIUS_M):
    """Place-recognition success: the share of queries with a known position whose best candidate lies
    within `radius_m` of it, and the mean error [m] of those hits (NaN when none).

    Args:
        best: (Q, D) best candidate position per query [m] (NaN = no candidate: a miss).
        truth: (Q, D) true query positions [m] (a NaN row = unknown, not counted).

    Returns:
        (success rate in [0, 1], mean error of the hits [m]).
    """
    known = np.isfinite(truth).all(axis=1)
    err = np.linalg.norm(best - truth, axis=1)
    hit = known & (err < radius_m)
    return float(hit.sum() / max(known.sum(), 1)), float(np.mean(err[hit])) if hit.any() else float("nan")
