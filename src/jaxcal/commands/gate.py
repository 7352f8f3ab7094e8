"""`jaxcal gate DB.h5 QUERIES.h5 --anchors RESULT.h5 [-o OUT.h5] [--json]`: UWB range-zone gated
place recognition (second paper, Section III-D); `jaxcal gate --simulate DIR` writes a simulated
repetitive yard (the three input files) and runs on it.

File layout (optional extension groups; every file is also a valid contract file, CONTRACT.md 1):

- DB.h5: any jaxcal file (the simulator writes the prior mapping run as a `trajectory` file, so that
  `jaxcal calibrate DB.h5 --method gp` calibrates the anchors from it) plus the group
  `places/`: `position` (K, D) float64 keyframe positions [m], `descriptor` (K, F) float
  (one descriptor per keyframe, any place-recognition method), attribute `metric` = `cosine` | `l2`.
- QUERIES.h5: any jaxcal file plus the group `queries/`: `descriptor` (Q, F); optional `id` (Q,)
  strings, `truth` (Q, D) float64 true positions [m] (NaN = unknown; enables the success rate), and
  the ranges, either explicitly as `range` (Q, A') float32 [m] (NaN = not heard) with `anchor_id`
  (A',) strings naming the columns, or, for a `trajectory` file, `time` (Q,) [s]: the contract
  ranges (`ranges/time`, `ranges/anchor`, `ranges/range`) within --window of a query time are
  assigned to it
  (median per anchor), anchors named by `anchors/id`.
- RESULT.h5: a contract `result` (e.g. from `jaxcal calibrate --method gp`): anchor `ids`,
  `position`, optional `covariance` (its largest eigenvalue widens the zones). Ranges to anchors the
  result does
  not contain, or contains without an estimate, do not gate.
- OUT.h5: a contract `result` (method `gate`, frame `world`): `ids` = query ids, `position` = best
  candidate per query (NaN = none), plus `candidates/index` (Q, k) int32 keyframe indices
  (-1 = none),
  `candidates/distance` (Q, k) descriptor distances, `candidates/n_admissible` (Q,) int32.
"""

from __future__ import annotations

import dataclasses

SUCCESS_RADIUS_M = 8.5  # the paper's match criterion (Section IV-E)


@dataclasses.dataclass(frozen=True)
class GateSettings:
    """Zone widths settable with --set (see `jaxcal.trajectory.gating.GateParams`)."""

    delta_m: float = 3.0
    k_sigma: float = 2.0
    range_rel: float = 0.01


def add_arguments(p) -> None:
    p.add_argument("db", nargs="?", help="keyframe database (jaxcal file with a places/ group)")
    p.add_argument("queries", nargs="?", help="queries (jaxcal file with a queries/ group)")
    p.add_argument(
        "--anchors", default=None, metavar="RESULT.h5", help="calibrated anchors (result file)"
    )
    p.add_argument(
        "-o",
        "--output",
        default=None,
        metavar="OUT.h5",
        help="write ranked candidates (result file)",
    )
    from jaxcal.commands._common import add_output_flags

    add_output_flags(p, "print one JSON summary object")
    p.add_argument("--top-k", type=int, default=5, help="candidates per query (default 5)")
    p.add_argument(
        "--max-anchors",
        type=int,
        default=None,
        metavar="N",
        help="gate with the N shortest ranges only",
    )
    p.add_argument(
        "--window",
        type=float,
        default=0.1,
        metavar="S",
        help="range-to-query time window [s] (default 0.1)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="delta_m, k_sigma, range_rel",
    )
    p.add_argument(
        "--simulate",
        default=None,
        metavar="DIR",
        help="write a simulated yard to DIR and run on it",
    )
    p.add_argument(
        "--size",
        choices=("small", "paper"),
        default="paper",
        help="simulated yard size (default paper: 600 x 450 m)",
    )
    p.add_argument("--seed", type=int, default=0, help="simulation seed")
    p.add_argument(
        "--anchor-error",
        type=float,
        default=2.0,
        metavar="M",
        help="simulated calibration RMS error [m]",
    )


# ---------------------------------------------------------------- files


def _root_check(path: str) -> None:
    from jaxcal.io import hdf5

    hdf5.read_format(path)  # raises FormatError with one line for a non-jaxcal file


def _dataset(f, key: str, path: str, required: bool = True):
    import h5py

    from jaxcal.errors import FormatError

    if key not in f:
        if required:
            raise FormatError(f"{path}: missing dataset '{key}'")
        return None
    obj = f[key]
    if not isinstance(obj, h5py.Dataset):
        raise FormatError(f"{path}: '{key}' must be a dataset")
    if h5py.check_string_dtype(obj.dtype) is not None or obj.dtype.kind in "SO":
        return [s.decode() if isinstance(s, bytes) else str(s) for s in obj.asstr()[()]]
    return obj[()]


def read_db(path: str):
    """(positions (K, D), descriptors (K, F), metric) from the `places/` group of a jaxcal file."""
    import h5py
    import numpy as np

    from jaxcal.errors import FormatError

    _root_check(path)
    with h5py.File(path, "r") as f:
        if "places" not in f:
            raise FormatError(f"{path}: no 'places' group (not a keyframe database)")
        pos = np.asarray(_dataset(f, "places/position", path), dtype=np.float64)
        desc = np.asarray(_dataset(f, "places/descriptor", path))
        metric = f["places"].attrs.get("metric", "cosine")
        metric = metric.decode() if isinstance(metric, bytes) else str(metric)
    if pos.ndim != 2 or pos.shape[1] not in (2, 3) or pos.shape[0] < 1:
        raise FormatError(f"{path}: places/position must have shape (K, 2|3), got {pos.shape}")
    if desc.ndim != 2 or desc.shape[0] != pos.shape[0] or desc.dtype.kind not in "fiu":
        raise FormatError(
            f"{path}: places/descriptor must be numeric of shape ({pos.shape[0]}, F), "
            f"got {desc.shape}"
        )
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(desc))):
        raise FormatError(f"{path}: places/position and places/descriptor must be finite")
    if metric not in ("cosine", "l2"):
        raise FormatError(f"{path}: places metric must be 'cosine' or 'l2', got {metric!r}")
    return pos, desc, metric


def read_queries(path: str, window_s: float):
    """Query descriptors (Q, F), ranges (Q, A') [m], anchor ids, query ids, truth (Q, D) or None."""
    import h5py
    import numpy as np

    from jaxcal.errors import FormatError

    fmt = None
    _root_check(path)
    with h5py.File(path, "r") as f:
        fmt = f.attrs["jaxcal_format"]
        fmt = fmt.decode() if isinstance(fmt, bytes) else str(fmt)
        if "queries" not in f:
            raise FormatError(f"{path}: no 'queries' group (not a query file)")
        desc = np.asarray(_dataset(f, "queries/descriptor", path))
        if desc.ndim != 2 or desc.shape[0] < 1 or desc.dtype.kind not in "fiu":
            raise FormatError(
                f"{path}: queries/descriptor must be numeric of shape (Q, F), got {desc.shape}"
            )
        q = desc.shape[0]
        ids = _dataset(f, "queries/id", path, False) or [f"q{i}" for i in range(q)]
        truth = _dataset(f, "queries/truth", path, False)
        explicit = _dataset(f, "queries/range", path, False)
        qtime = _dataset(f, "queries/time", path, False)
        if explicit is not None:
            ranges = np.asarray(explicit, dtype=np.float64)
            anchor_ids = _dataset(f, "queries/anchor_id", path)
        elif qtime is not None and fmt == "trajectory":
            anchor_ids = _dataset(f, "anchors/id", path)
            ranges = _ranges_from_contract(
                np.asarray(qtime, np.float64),
                np.asarray(_dataset(f, "ranges/time", path), np.float64),
                np.asarray(_dataset(f, "ranges/anchor", path), np.int64),
                np.asarray(_dataset(f, "ranges/range", path), np.float64),
                len(anchor_ids),
                window_s,
            )
        else:
            raise FormatError(
                f"{path}: queries need 'queries/range' or 'queries/time' in a trajectory file"
            )
    if len(ids) != q:
        raise FormatError(f"{path}: queries/id has {len(ids)} entries for {q} descriptors")
    if ranges.shape != (q, len(anchor_ids)):
        raise FormatError(
            f"{path}: query ranges must have shape ({q}, {len(anchor_ids)}), got {ranges.shape}"
        )
    if np.any(ranges < 0) or np.any(np.isinf(ranges)):
        raise FormatError(f"{path}: query ranges must be non-negative (NaN = not heard)")
    if truth is not None:
        truth = np.asarray(truth, np.float64)
        if truth.ndim != 2 or truth.shape[0] != q:
            raise FormatError(f"{path}: queries/truth must have shape ({q}, D), got {truth.shape}")
    return desc, ranges, [str(a) for a in anchor_ids], [str(i) for i in ids], truth


def _ranges_from_contract(qtime, rtime, ranchor, rrange, n_anchors, window_s):
    """(Q, A) median of the ranges within window_s / 2 of each query time; NaN where none."""
    import numpy as np

    from jaxcal.errors import JaxcalError

    if window_s <= 0:
        raise JaxcalError(f"--window must be positive, got {window_s}")
    if np.any(ranchor < 0) or np.any(ranchor >= n_anchors):
        raise JaxcalError("ranges/anchor: index out of range")
    out = np.full((qtime.size, n_anchors), np.nan)
    lo = np.searchsorted(rtime, qtime - window_s / 2, side="left")
    hi = np.searchsorted(rtime, qtime + window_s / 2, side="right")
    for i in range(qtime.size):
        a, r = ranchor[lo[i] : hi[i]], rrange[lo[i] : hi[i]]
        for j in np.unique(a):
            v = r[(a == j) & np.isfinite(r)]
            if v.size:
                out[i, j] = np.median(v)
    return out


def write_places_files(directory, scene, anchor_error_m: float, seed: int):
    """Write a simulated scene as DB, queries and anchors files into `directory`; return paths."""
    from pathlib import Path

    import h5py
    import numpy as np

    from jaxcal.data import Result, TrajectoryDataset
    from jaxcal.errors import JaxcalError
    from jaxcal.io import hdf5
    from jaxcal.io.atomic import atomic_path
    from jaxcal.sim.places import perturb_anchors

    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise JaxcalError(f"{d}: exists and is not a folder")
    d.mkdir(parents=True, exist_ok=True)
    a = scene.anchor_truth.shape[0]
    anchor_ids = [f"A{i}" for i in range(a)]

    def trajectory(name, time, pos, rng_matrix, los=None):
        qi, ai = np.nonzero(np.isfinite(rng_matrix))
        return TrajectoryDataset(
            name=name,
            anchor_ids=anchor_ids,
            tag_ids=["T0"],
            lever_arm=np.zeros((1, 3)),
            pose_time=time,
            pose_position=pos,
            range_time=time[qi],
            range_anchor=ai,
            range_tag=np.zeros(qi.size),
            range=rng_matrix[qi, ai],
            anchor_truth=scene.anchor_truth,
            range_los=None if los is None else los[qi, ai].astype(np.int8),
            source="jaxcal.sim.places",
            description="simulated repetitive container yard",
        )

    def write_with(path, obj, group, items, attrs=None):
        with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
            hdf5.write_open(f, obj)
            g = f.create_group(group)
            for k, v in items.items():
                if isinstance(v, list):
                    g.create_dataset(
                        k, data=np.array(v, dtype=object), dtype=h5py.string_dtype()
                    )
                else:
                    g.create_dataset(k, data=v)
            for k, v in (attrs or {}).items():
                g.attrs[k] = v

    db_path, q_path, an_path = d / "places_db.h5", d / "places_queries.h5", d / "places_anchors.h5"
    write_with(
        db_path,
        trajectory(
            "places-prior", scene.keyframe_time, scene.keyframe_position, scene.keyframe_range
        ),
        "places",
        {"position": scene.keyframe_position, "descriptor": scene.keyframe_descriptor},
        {"metric": "cosine"},
    )
    q = scene.query_time.size
    write_with(
        q_path,
        trajectory(
            "places-queries",
            scene.query_time,
            scene.query_position,
            scene.query_range,
            scene.query_los,
        ),
        "queries",
        {
            "descriptor": scene.query_descriptor,
            "time": scene.query_time,
            "truth": scene.query_position,
            "id": [f"q{i}" for i in range(q)],
        },
    )
    pos, cov = perturb_anchors(np.random.default_rng(seed + 1), scene.anchor_truth, anchor_error_m)
    hdf5.write(
        an_path,
        Result(
            ids=anchor_ids,
            position=pos,
            covariance=cov,
            method="simulated",
            dataset="places-prior",
            frame="world",
            params={"anchor_error_m": anchor_error_m, "seed": seed},
        ),
    )
    return str(db_path), str(q_path), str(an_path)


# ---------------------------------------------------------------- run


def run(args) -> int:
    import time

    import numpy as np

    from jaxcal.commands._common import load, print_json
    from jaxcal.errors import JaxcalError
    from jaxcal.params import parse_set, with_overrides

    settings = with_overrides(GateSettings(), parse_set(args.set))
    for k, v in dataclasses.asdict(settings).items():
        if not np.isfinite(v) or v < 0:
            raise JaxcalError(f"parameter {k}: must be a non-negative number, got {v}")
    if args.top_k < 1:
        raise JaxcalError(f"--top-k must be >= 1, got {args.top_k}")
    if args.max_anchors is not None and args.max_anchors < 0:
        raise JaxcalError(f"--max-anchors must be >= 0, got {args.max_anchors}")

    from jaxcal.commands._common import check_inputs, check_output_path

    inputs = [args.db, args.queries, args.anchors]
    check_inputs(inputs)
    out = check_output_path(args.output, inputs) if args.output else None
    if args.simulate is not None:
        check_output_path(args.simulate, folder=True)
        if args.db or args.queries or args.anchors:
            raise JaxcalError(
                "--simulate writes its own DB, queries and anchors; give no input files"
            )
        from jaxcal.sim.places import PlaceConfig, simulate_places

        cfg = (
            PlaceConfig()
            if args.size == "paper"
            else PlaceConfig(
                width_m=150.0,
                height_m=100.0,
                cross_pitch_m=50.0,
                descriptor_dim=64,
                n_anchors_x=2,
                n_anchors_y=2,
                max_range_m=150.0,
            )
        )
        scene = simulate_places(args.seed, cfg, n_queries=500 if args.size == "paper" else 60)
        db_file, q_file, an_file = write_places_files(
            args.simulate, scene, args.anchor_error, args.seed
        )
    else:
        if not (args.db and args.queries and args.anchors):
            raise JaxcalError("need DB.h5 QUERIES.h5 --anchors RESULT.h5 (or --simulate DIR)")
        db_file, q_file, an_file = args.db, args.queries, args.anchors

    import jax.numpy as jnp

    from jaxcal.trajectory import gating

    kf_pos, kf_desc, metric = read_db(db_file)
    q_desc, q_range, q_anchor_ids, q_ids, truth = read_queries(q_file, args.window)
    if q_desc.shape[1] != kf_desc.shape[1]:
        raise JaxcalError(
            f"{q_file}: descriptors have {q_desc.shape[1]} components, "
            f"database has {kf_desc.shape[1]}"
        )
    result = load(an_file, ("result",))
    dim = result.position.shape[1]
    if dim > kf_pos.shape[1]:
        raise JaxcalError(f"{an_file}: anchors are {dim}-D but keyframes are {kf_pos.shape[1]}-D")
    if args.top_k > kf_pos.shape[0]:
        raise JaxcalError(f"--top-k {args.top_k} exceeds the {kf_pos.shape[0]} keyframes")

    # Columns of the query ranges -> rows of the result; unknown ids do not gate.
    row = {aid: i for i, aid in enumerate(result.ids)}
    cols = [row.get(a) for a in q_anchor_ids]
    known = [i for i, c in enumerate(cols) if c is not None]
    unmatched = [a for a, c in zip(q_anchor_ids, cols, strict=True) if c is None]
    a_pos = np.full((len(cols), dim), np.nan)
    a_cov = np.zeros((len(cols), dim, dim))
    for i in known:
        a_pos[i] = result.position[cols[i]]
        if result.covariance is not None:
            a_cov[i] = result.covariance[cols[i]]
    ranges = q_range.copy()
    if args.max_anchors is not None:
        order = np.argsort(np.where(np.isfinite(ranges), ranges, np.inf), axis=1)
        drop = order[:, args.max_anchors :]
        np.put_along_axis(ranges, drop, np.nan, axis=1)

    db = gating.KeyframeDB.build(kf_pos[:, :dim], kf_desc, metric)
    anchors = gating.Anchors.from_estimate(a_pos, a_cov)
    index = gating.ZoneIndex.build(db, anchors)
    params = gating.GateParams(**dataclasses.asdict(settings))
    t0 = time.perf_counter()
    cand = gating.search(db, index, anchors, q_desc, ranges, params, top_k=args.top_k)
    elapsed = time.perf_counter() - t0
    c_index = np.asarray(cand.index)
    best = np.where(c_index[:, :1] >= 0, kf_pos[np.maximum(c_index[:, 0], 0)], np.nan)
    usable = np.isfinite(ranges) & np.isfinite(a_pos).all(axis=1)[None, :]

    summary = {
        "db": db_file,
        "queries": q_file,
        "anchors": an_file,
        "keyframes": int(kf_pos.shape[0]),
        "n_queries": len(q_ids),
        "top_k": args.top_k,
        "metric": metric,
        "params": dataclasses.asdict(settings),
        "anchors_unmatched": unmatched,
        "mean_anchors_heard": float(usable.sum(1).mean()),
        "queries_without_range": int((usable.sum(1) == 0).sum()),
        "mean_admissible": float(np.asarray(cand.n_admissible).mean()),
        "seconds_incl_compile": elapsed,
    }
    if truth is not None:
        full = gating.search_full(db, jnp.asarray(q_desc), top_k=1)
        tq = truth[:, : kf_pos.shape[1]]
        ok_t = np.isfinite(tq).all(axis=1)

        def rate(best_pos):
            err = np.linalg.norm(best_pos - tq, axis=1)
            hit = ok_t & (err < SUCCESS_RADIUS_M)
            return float(hit.sum() / max(ok_t.sum(), 1)), float(
                np.mean(err[hit])
            ) if hit.any() else float("nan")

        summary["success_gated"], summary["error_gated_m"] = rate(best)
        summary["success_full"], summary["error_full_m"] = rate(
            kf_pos[np.asarray(full.index)[:, 0]]
        )
        summary["queries_with_truth"] = int(ok_t.sum())

    if args.output:
        _write_output(args.output, q_ids, best, cand, settings, q_file, args.top_k)
        summary["output"] = args.output
        summary["overwrote"] = out.existed
    if args.json:
        print_json(summary)
    elif not args.quiet:
        line = (
            f"gate: {len(q_ids)} queries against {kf_pos.shape[0]} keyframes, "
            f"{summary['mean_anchors_heard']:.2f} anchors heard, "
            f"{summary['mean_admissible']:.0f} admissible on average"
        )
        if truth is not None:
            g, f = summary["success_gated"], summary["success_full"]
            line += f"; success gated {g:.1%} vs full {f:.1%}"
        print(line + (f" -> {args.output}{out.note()}" if args.output else ""))
    return 0


def _write_output(path, q_ids, best, cand, settings, q_file, top_k) -> None:
    from pathlib import Path

    import h5py
    import numpy as np

    from jaxcal.data import Result
    from jaxcal.errors import JaxcalError
    from jaxcal.io import hdf5
    from jaxcal.io.atomic import atomic_path

    p = Path(path)
    if not p.parent.exists():
        raise JaxcalError(f"{p}: folder {p.parent} does not exist")
    res = Result(
        ids=q_ids,
        position=best,
        method="gate",
        dataset=Path(q_file).stem,
        frame="world",
        params={**dataclasses.asdict(settings), "top_k": top_k},
    )
    with atomic_path(p) as tmp, h5py.File(tmp, "w") as f:
        hdf5.write_open(f, res)
        g = f.create_group("candidates")
        g.create_dataset("index", data=np.asarray(cand.index, np.int32))
        g.create_dataset("distance", data=np.asarray(cand.distance, np.float64))
        g.create_dataset("n_admissible", data=np.asarray(cand.n_admissible, np.int32))
