"""`jaxcal calibrate DATASET.h5 --method M -o RESULT.h5 [--config NAME] [--set K=V ...] [--params P.json]`."""

from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("dataset", help="a mesh or trajectory file")
    p.add_argument("--method", required=True, help="mesh: cf, pgp, ...; trajectory: gp, nls, ls, ...")
    p.add_argument("-o", "--output", required=True, help="result file to write")
    p.add_argument("--config", default=None, help="mesh frame configuration (configs/<NAME>; 'auto': the best-connected, best-conditioned triple); default (0, 1, 2)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a method parameter")
    p.add_argument("--params", default=None, metavar="PARAMS.json", help="parameters from a JSON file (e.g. from `jaxcal tune`)")
    p.add_argument("--json", action="store_true", help="print a JSON summary of the result")


def run(args) -> int:
    import time

    from jaxcal.commands._common import load, print_json
    from jaxcal.io import hdf5
    from jaxcal.methods import calibrate
    from jaxcal.params import load_params_json, parse_set

    ds = load(args.dataset, ("mesh", "trajectory"))
    params = load_params_json(args.params) if args.params else {}
    params.update(parse_set(args.set))
    from jaxcal.data import MeshDataset

    mesh = isinstance(ds, MeshDataset)
    if mesh and args.config == "auto":
        from jaxcal.mesh.identify import with_auto_config

        ds, tri = with_auto_config(ds)
        if not args.json:
            print("config auto: " + "/".join(ds.node_ids[i] for i in tri) + f" (nodes {tri[0]}, {tri[1]}, {tri[2]})")
    t0 = time.perf_counter()
    result = calibrate(ds, args.method, params=params, config=args.config)
    elapsed = time.perf_counter() - t0
    hdf5.write(args.output, result)
    import numpy as np

    est = np.isfinite(result.position).all(axis=1)
    n_est, n = int(est.sum()), len(result.ids)
    missing = [result.ids[i] for i in np.flatnonzero(~est)]
    fixed = None
    if mesh and result.frame_anchors() is not None:
        from jaxcal.mesh.identify import identify_ranges

        fixed = identify_ranges(ds.range, result.frame_anchors(), result.position.shape[1], ids=ds.node_ids).fixed
    if args.json:
        print_json({"method": result.method, "dataset": result.dataset, "output": args.output,
                    "estimated": n_est, "nodes": n, "not_placed": n - n_est, "not_placed_ids": missing,
                    "fixed_by_ranges": None if fixed is None else int(fixed.sum()), "seconds": elapsed})
    else:
        print(_summary(args.method, result.ids, est, fixed) + f" in {elapsed:.2f} s -> {args.output}")
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
