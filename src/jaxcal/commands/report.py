"""`jaxcal report FILE.h5 [FILE.h5 ...] [--truth DATASET.h5] -o DIR [--posteriors SPEC]
[--sweep-metric M] [--sweep-others best|facet]`.

Writes the papers' figures as PNG files and an `index.html` that shows them with their numbers
(see `jaxcal.report`). Each FILE is a calibration result (contract format `result`) or a sweep
file of `jaxcal sweep`, told apart by their layout (a sweep file has `runs/`, `metrics/`, `done`).

Results are grouped by (method, configuration) and need `--truth`. Posterior grids (Fig. 6 style)
are recomputed by re-running PGP on the first epochs of the dataset: `--posteriors auto` (default),
`none`, or `NODE,NODE@EPOCH,EPOCH` (e.g. `D5B4,9911@5,20,100`).

Sweeps need no truth: each (scenario, config) of a sweep gives the surface of `--sweep-metric`
(default `rmse_m`) over sigma_r x tau, averaged over seeds; other swept parameters are set per cell
to their best value (`--sweep-others best`, default) or give one surface each (`facet`). Of sigma_r
and tau, one that is not swept is drawn as a single row at its fixed value.
"""

from __future__ import annotations

SWEEP_HELP = (
    "FILE: calibration results of one dataset (need --truth) and/or sweep files of `jaxcal sweep` "
    "(detected by layout: runs/, metrics/, done)"
)


def add_arguments(p) -> None:
    p.add_argument("files", nargs="+", metavar="FILE.h5", help=SWEEP_HELP)
    p.add_argument(
        "--truth",
        default=None,
        metavar="DATASET.h5",
        help="the dataset with ground truth (required with results; optional for sweeps only)",
    )
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="folder to write (created)")
    p.add_argument(
        "--posteriors",
        default="auto",
        help="posterior grids: auto (default), none, or NODE,...@EPOCH,... (re-runs PGP)",
    )
    p.add_argument(
        "--label",
        action="append",
        default=None,
        metavar="TEXT",
        help="label of each result in order (repeat; default method/configuration)",
    )
    p.add_argument(
        "--sweep-metric",
        default="rmse_m",
        choices=["rmse_m", "final_rmse_m", "nlpl"],
        help="metric of the sweep surfaces (rmse_m: every epoch estimate, as jaxcal evaluate)",
    )
    p.add_argument(
        "--sweep-others",
        default="best",
        choices=["best", "facet"],
        help="other swept parameters (sigma_v, ...): best value per cell, or one surface each",
    )
    from jaxcal.commands._common import add_output_flags

    add_output_flags(p, "print the report's numbers as one JSON object")


def is_sweep_file(path: str) -> bool:
    """Whether `path` is an HDF5 file with the layout of `jaxcal sweep` (False otherwise)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return all(k in f for k in ("runs", "metrics", "done")) and "jaxcal_format" not in f.attrs
    except OSError:
        return False


def sweep_file_surfaces(path: str, metric: str = "rmse_m", others: str = "best") -> list[dict]:
    """The sigma_r x tau surfaces of a sweep file (`jaxcal.report.sweep_surfaces`)."""
    import ast

    from jaxcal.commands.sweep import read_store
    from jaxcal.errors import JaxcalError
    from jaxcal.report import sweep_surfaces

    attrs, runs, metrics, done = read_store(path)
    fixed = {}
    try:
        fixed = dict(ast.literal_eval(str(attrs.get("fixed_params", "{}"))))
    except (ValueError, SyntaxError):
        raise JaxcalError(f"{path}: unreadable fixed_params attribute") from None
    if not {"param_sigma_r", "param_tau"} <= set(runs):  # an unswept one: its fixed or default value
        from jaxcal.mesh.pgp import PGPParams

        fixed = {k: fixed.get(k, getattr(PGPParams(), k)) for k in ("sigma_r", "tau")}
    if "scenario" not in runs or len(done) != len(runs["scenario"]):
        raise JaxcalError(f"{path}: inconsistent sweep file (runs/scenario and done differ)")
    return sweep_surfaces(
        runs,
        metrics,
        done,
        metric=metric,
        others=others,
        fixed=fixed,
        method=str(attrs.get("method", "")),
    )


def run(args) -> int:
    import json
    import time

    from jaxcal.commands._common import check_inputs, check_output_path, load, print_json
    from jaxcal.errors import JaxcalError
    from jaxcal.report import parse_posteriors, write_report

    t0 = time.perf_counter()
    check_inputs(args.files, args.truth)
    check_output_path(args.output, folder=True)
    spec = parse_posteriors(args.posteriors)
    sweeps, result_paths = [], []
    for path in args.files:
        if is_sweep_file(path):
            sweeps += sweep_file_surfaces(path, args.sweep_metric, args.sweep_others)
        else:
            result_paths.append(path)
    truth = load(args.truth, ("mesh", "trajectory")) if args.truth is not None else None
    results = [load(path, ("result",)) for path in result_paths]
    if results and truth is None:
        raise JaxcalError("calibration results need --truth DATASET.h5")
    from jaxcal.data import MeshDataset
    from jaxcal.progress import progress_bar
    from jaxcal.report import report_sections

    total = report_sections(truth is not None, len(results), isinstance(truth, MeshDataset), len(sweeps))
    with progress_bar(total, "report", "section", enabled=not (args.quiet or args.json)) as bar:
        index = write_report(
            results,
            truth,
            args.output,
            labels=args.label,
            posteriors=spec,
            sweeps=sweeps,
            progress=bar.update,
        )
    seconds = time.perf_counter() - t0
    if args.json:
        numbers = json.loads((index.parent / "report.json").read_text())
        print_json({"index": str(index), "seconds": seconds, **numbers})
    elif not args.quiet:
        print(f"report in {index} ({seconds:.1f} s)")
    return 0
