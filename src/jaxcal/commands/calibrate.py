"""`jaxcal calibrate DATASET.h5 --method M -o RESULT.h5 [--config NAME|A0,A1,A2] [--set K=V ...] [--params P.json]`.

`jaxcal calibrate --method M --list-params` prints the method's parameters (default, unit, meaning).
"""

from __future__ import annotations


def add_arguments(p) -> None:
    from jaxcal.commands._common import CONFIG_HELP, add_output_flags

    p.add_argument("dataset", nargs="?", help="a mesh or trajectory file")
    p.add_argument("--method", required=True, help="mesh: cf, pgp, ...; trajectory: gp, nls, ls, ...")
    p.add_argument("-o", "--output", default=None, help="result file to write (required)")
    p.add_argument("--config", default=None, help=CONFIG_HELP + " 'auto': the best-connected, best-conditioned triple.")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a method parameter")
    p.add_argument(
        "--params", default=None, metavar="PARAMS.json", help="parameters from a JSON file (e.g. from `jaxcal tune`)"
    )
    p.add_argument(
        "--list-params", action="store_true", help="print the method's parameters (default, unit, meaning) and exit"
    )
    add_output_flags(p, "print a JSON summary of the result")


def list_params(args) -> int:
    from jaxcal.commands._common import print_json
    from jaxcal.methods import param_defaults
    from jaxcal.params import describe

    stages = param_defaults(args.method)
    rows = []
    for d in stages:
        prefix = f"{'pgp' if 'PGP' in type(d).__name__ else 'batch'}." if len(stages) > 1 else ""
        rows += [{**r, "name": prefix + r["name"]} for r in describe(d)]
    if args.json:
        print_json({"method": args.method, "params": rows})
        return 0
    print(f"parameters of --method {args.method} (set with --set KEY=VALUE):")
    width = max(len(r["name"]) for r in rows)
    for r in rows:
        default = repr(r["default"]) if isinstance(r["default"], str) else str(r["default"])
        unit = f" [{r['unit']}]" if r["unit"] else ""
        print(f"  {r['name']:<{width}}  {default + unit:<16}  {r['meaning']}")
    if len(stages) > 1:
        print("  (a name without the pgp./batch. prefix sets it in every stage that has it)")
    return 0


def run(args) -> int:
    import time

    from jaxcal.commands._common import check_inputs, check_output_path, emit_json, load, resolve_config, say
    from jaxcal.errors import JaxcalError
    from jaxcal.methods import calibrate, get_method
    from jaxcal.params import load_params_json, parse_set

    if args.list_params:
        return list_params(args)
    if args.dataset is None or args.output is None:
        raise JaxcalError("calibrate needs DATASET.h5 and -o RESULT.h5 (or --list-params)")
    check_inputs(args.dataset, args.params)
    out = check_output_path(args.output, [args.dataset, args.params])  # paths first: no import, no read
    from jaxcal.io import hdf5

    ds = load(args.dataset, ("mesh", "trajectory"))
    get_method("mesh" if hasattr(ds, "node_ids") else "trajectory", args.method)  # unknown method: now
    params = load_params_json(args.params) if args.params else {}
    params.update(parse_set(args.set))
    from jaxcal.data import MeshDataset

    mesh = isinstance(ds, MeshDataset)
    if mesh and args.config == "auto":
        from jaxcal.mesh.frame_choice import with_auto_config

        ds, tri = with_auto_config(ds)
        say(args, "config auto: " + "/".join(ds.node_ids[i] for i in tri) + f" (nodes {tri[0]}, {tri[1]}, {tri[2]})")
    ds, config = resolve_config(ds, args.config)
    t0 = time.perf_counter()
    from jaxcal.methods import WITH_PROGRESS
    from jaxcal.progress import progress_bar

    quiet = args.quiet or args.json
    stages = _stages(args.method, params)
    if stages:  # a stage-level bar (tqdm on a terminal; silent under --quiet, --json or a pipe)
        fn = get_method("mesh" if hasattr(ds, "node_ids") else "trajectory", args.method)
        with progress_bar(stages, args.method, "stage", enabled=not quiet) as bar:
            result = fn(ds, params=params, config=config, progress=bar.update)
    elif args.method in WITH_PROGRESS and isinstance(ds, MeshDataset):  # a bar over the filter's epochs
        with progress_bar(ds.n_epochs, args.method, "epoch", enabled=not quiet) as bar:
            result = calibrate(ds, args.method, params=params, config=config, progress=bar.update)
    else:
        result = calibrate(ds, args.method, params=params, config=config)
    elapsed = time.perf_counter() - t0
    hdf5.write(out.path, result)
    import numpy as np

    from jaxcal.metrics import predicted_uncertainty

    est = np.isfinite(result.position).any(axis=1)  # placed; a row with a NaN coordinate counts in `partial`
    n_est, n = int(est.sum()), len(result.ids)
    missing = [result.ids[i] for i in np.flatnonzero(~est)]
    fixed = None
    if mesh and result.frame_anchors() is not None:
        from jaxcal.mesh.identify import identify_ranges

        fixed = identify_ranges(ds.range, result.frame_anchors(), result.position.shape[1], ids=ds.node_ids).fixed
    pu = predicted_uncertainty(result)
    pred = pu["predicted_rmse_m"]
    emit_json(
        args,
        {
            "method": result.method,
            "dataset": result.dataset,
            "output": args.output,
            "estimated": n_est,
            "nodes": n,
            "not_placed": n - n_est,
            "not_placed_ids": missing,
            "fixed_by_ranges": None if fixed is None else int(fixed.sum()),
            "seconds": elapsed,
            "overwrote": out.existed,
            "partial": pu["partial"],
            "predicted_rmse_m": pred if np.isfinite(pred) else None,
        },
    )
    some = est & ~np.isfinite(result.position).all(axis=1)
    named = ", ".join(result.ids[i] for i in np.flatnonzero(some)[:8]) + (", ..." if some.sum() > 8 else "")
    partial = f" ({pu['partial']} with a coordinate not fixed: {named})" if pu["partial"] else ""
    quality = f", predicted RMS uncertainty {pred:.3g} m" if np.isfinite(pred) else ", no covariance"
    drift_used = bool(result.params.get("info_pose_error_propagated", False))
    estimated = "info_pose_error_model" in result.params  # nls or gp looked for a shared pose error in the ranges
    if not mesh and np.isfinite(pred) and not _pose_error_stated(params) and not drift_used:
        seen = "the ranges show no shared pose error; otherwise " if estimated else ""
        or_estimate = ", or --set estimate_drift=true" if args.method in ("nls", "gp") and not estimated else ""
        quality += (
            f" ({seen}poses taken as exact: state their error with --set pose_drift=... / pose_sd_m=...{or_estimate})"
        )
    elif not mesh and np.isfinite(pred) and drift_used:
        widened = float(result.params.get("info_pose_error_widened", 1.0))
        quality += (
            f" (with {_estimated_pose_error(result.params)} estimated from the ranges: sd widened up to x{widened:.2f})"
        )
    say(
        args,
        _summary(args.method, result.ids, est, fixed) + f"{partial}{quality} in {elapsed:.2f} s "
        f"-> {args.output}{out.note()}",
    )
    return 0


def _estimated_pose_error(params: dict) -> str:
    """What `nls` or `gp` propagated of the pose error estimated (`jaxcal.trajectory.drift`), in words."""
    if params.get("info_pose_error_model") == "bounded":
        sd, corr = (params.get(f"info_pose_bounded_{k}", float("nan")) for k in ("sd_m", "corr_s"))
        return f"a bounded pose error of sd {sd:.3g} m over {corr:.0f} s"
    return f"a pose drift of {params.get('info_pose_drift_upper', float('nan')):.3g} m/sqrt(s)"


def _pose_error_stated(params: dict) -> bool:
    """Whether the run was told the platform's pose error (`jaxcal.trajectory.pose_error`): without it a
    trajectory covariance holds the range noise only, and drift shared by a stretch of the path is not in it."""
    for key in ("pose_sd_m", "pose_drift"):
        try:
            if float(params.get(key, 0.0)) > 0.0:
                return True
        except (TypeError, ValueError):
            return False
    return False


def _stages(method: str, params: dict) -> int:
    """Progress units of a method that reports stages (batch, gp); 0 for the others."""
    from jaxcal.params import with_overrides

    if method == "batch":
        from jaxcal.mesh.batch import BatchParams, stage_count

        return stage_count(with_overrides(BatchParams(), params))
    if method == "gp":
        from jaxcal.trajectory.gp import GPParams

        p = with_overrides(GPParams(), params)
        return 1 if p.mean == "anchor" else p.stages
    return 0


def _summary(method: str, ids, est, fixed) -> str:
    """The summary line: a success line only when every node was placed; otherwise how many were not,
    and which of them the ranges would have fixed (a method placing fewer than it could)."""
    n, n_est = len(ids), int(est.sum())
    line = f"{method}: {n_est}/{n} positions estimated"
    if n_est == n:
        return line
    line += f", {n - n_est} NOT placed"
    if fixed is None:
        return line + " (" + ", ".join(ids[i] for i in range(n) if not est[i]) + ")"
    could = [ids[i] for i in range(n) if fixed[i] and not est[i]]
    cannot = [ids[i] for i in range(n) if not fixed[i] and not est[i]]
    parts = []
    if cannot:
        parts.append("not fixed by the ranges: " + ", ".join(cannot))
    if could:
        parts.append(f"fixed by the ranges but not placed by {method}: " + ", ".join(could))
    return line + " (" + "; ".join(parts) + ")"
