"""`jaxcal gate DB.h5 QUERIES.h5 --anchors RESULT.h5 [-o OUT.h5] [--json]`: UWB range-zone gated
place recognition (second paper, Section III-D); `jaxcal gate --simulate DIR` writes a simulated
repetitive yard (the three input files) and runs on it.

Orchestration only: the files (DB.h5 with a `places/` group, QUERIES.h5 with a `queries/` group, the
anchors' RESULT.h5, OUT.h5 with a `candidates/` group; layouts in `jaxcal.io.places`) are read and written
by `jaxcal.io.places`, the gating is `jaxcal.trajectory.gating` (zone widths `GateParams`, settable with
--set), the success rate `jaxcal.metrics.place_success`.
"""

from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("db", nargs="?", help="keyframe database (jaxcal file with a places/ group)")
    p.add_argument("queries", nargs="?", help="queries (jaxcal file with a queries/ group)")
    p.add_argument("--anchors", default=None, metavar="RESULT.h5", help="calibrated anchors (result file)")
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


def run(args) -> int:
    import time

    import numpy as np

    from jaxcal.commands._common import load, print_json
    from jaxcal.errors import JaxcalError
    from jaxcal.io import places
    from jaxcal.params import as_dict, parse_set, with_overrides
    from jaxcal.trajectory import gating

    params = with_overrides(gating.GateParams(), parse_set(args.set))
    settings = as_dict(params)
    for k, v in settings.items():
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
            raise JaxcalError("--simulate writes its own DB, queries and anchors; give no input files")
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
        db_file, q_file, an_file = places.write_places_files(args.simulate, scene, args.anchor_error, args.seed)
    else:
        if not (args.db and args.queries and args.anchors):
            raise JaxcalError("need DB.h5 QUERIES.h5 --anchors RESULT.h5 (or --simulate DIR)")
        db_file, q_file, an_file = args.db, args.queries, args.anchors

    import jax.numpy as jnp

    from jaxcal.metrics import place_success

    kf_pos, kf_desc, metric = places.read_db(db_file)
    q_desc, q_range, q_anchor_ids, q_ids, truth = places.read_queries(q_file, args.window)
    if q_desc.shape[1] != kf_desc.shape[1]:
        raise JaxcalError(f"{q_file}: descriptors have {q_desc.shape[1]} components, database has {kf_desc.shape[1]}")
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
    t0 = time.perf_counter()
    cand = gating.search(db, index, anchors, q_desc, ranges, params, top_k=args.top_k)
    elapsed = time.perf_counter() - t0
    c_index = np.asarray(cand.index)
    best = np.where(c_index[:, :1] >= 0, kf_pos[np.maximum(c_index[:, 0], 0)], np.nan)
    usable = np.isfinite(ranges) & np.asarray(np.isfinite(a_pos).all(axis=1))[None, :]

    summary = {
        "db": db_file,
        "queries": q_file,
        "anchors": an_file,
        "keyframes": int(kf_pos.shape[0]),
        "n_queries": len(q_ids),
        "top_k": args.top_k,
        "metric": metric,
        "params": settings,
        "anchors_unmatched": unmatched,
        "mean_anchors_heard": float(usable.sum(1).mean()),
        "queries_without_range": int((usable.sum(1) == 0).sum()),
        "mean_admissible": float(np.asarray(cand.n_admissible).mean()),
        "seconds_incl_compile": elapsed,
    }
    if truth is not None:
        full = gating.search_full(db, jnp.asarray(q_desc), top_k=1)
        tq = truth[:, : kf_pos.shape[1]]
        summary["success_gated"], summary["error_gated_m"] = place_success(best, tq)
        summary["success_full"], summary["error_full_m"] = place_success(kf_pos[np.asarray(full.index)[:, 0]], tq)
        summary["queries_with_truth"] = int(np.isfinite(tq).all(axis=1).sum())

    if args.output:
        from pathlib import Path

        assert out is not None  # checked before the work, with the output

        places.write_candidates(args.output, q_ids, best, cand, {**settings, "top_k": args.top_k}, Path(q_file).stem)
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
        print(line + (f" -> {args.output}{out.note()}" if out is not None else ""))
    return 0
