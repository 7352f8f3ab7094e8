"""`jaxcal import FORMAT SRC... -o OUT [--name NAME] [--force] [--json] [--quiet]`: convert a recording.

Forms (scripts rely on them):
    jaxcal import dwm1001-autocal SCENARIO_DIR NODES_CFG.yaml -o OUT
    jaxcal import hymn DATASET_ROOT -o OUT          (the folder holding data/)
    jaxcal import cuhksz UWB.csv MOCAP.csv -o OUT
    jaxcal import hanyang RUN_DIR -o OUT
    jaxcal import csv FILE -o OUT

The import is cross-checked (`_checks.truth_consistency`): a layout (truth) whose distances do not fit
the ranges (median |range - layout distance| above `LAYOUT_MISMATCH_M`) or whose ids never range is
refused with one line, unless `--force`.
"""

from __future__ import annotations

_FORMATS = "dwm1001-autocal, hymn, cuhksz, hanyang, csv"


def add_arguments(p) -> None:
    from jaxcal.commands._common import add_output_flags

    p.add_argument("format", metavar="FORMAT", help=f"recording format: {_FORMATS}")
    p.add_argument("sources", metavar="SRC", nargs="+", help="source file(s) or folder(s) of the recording")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="jaxcal HDF5 file to write")
    p.add_argument("--name", default=None, help="dataset name (default: derived from the source)")
    p.add_argument(
        "--force",
        action="store_true",
        help="write the file even when the layout (truth) does not fit the ranges or its ids",
    )
    add_output_flags(p)


def run(args) -> int:
    import time

    from jaxcal.commands._checks import truth_consistency
    from jaxcal.commands._common import check_output_path, emit_json, kind_of, say
    from jaxcal.errors import JaxcalError
    from jaxcal.io import hdf5
    from jaxcal.io.importers import import_recording

    t0 = time.perf_counter()
    out = check_output_path(args.output, args.sources)
    ds = import_recording(args.format, *args.sources, name=args.name, force=args.force)
    check = truth_consistency(ds)
    if check is not None and check["problems"] and not args.force:
        raise JaxcalError(f"not written: {check['problems'][0]} (--force writes it anyway)")
    hdf5.write(out.path, ds)
    kind = kind_of(ds)
    summary = {"file": str(out), "format": kind, "name": ds.name, "importer": args.format}
    if kind == "mesh":
        import numpy as np

        summary.update(nodes=ds.n_nodes, epochs=ds.n_epochs, ranges=int(np.isfinite(ds.range).sum()))
    else:
        summary.update(anchors=ds.n_anchors, tags=len(ds.tag_ids), poses=int(ds.pose_time.shape[0]), ranges=ds.n_ranges)
    summary["description"] = ds.description
    if check is not None:
        summary["layout_median_m"] = check["median_m"]
        summary["layout_problems"] = check["problems"]
    summary["overwrote"] = out.existed
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    emit_json(args, summary)
    counts = ", ".join(
        f"{k} {summary[k]}" for k in ("nodes", "epochs", "anchors", "tags", "poses", "ranges") if k in summary
    )
    say(args, f"wrote {out}: {kind} '{ds.name}' ({counts}) in {summary['seconds']:.2f} s{out.note()}")
    if ds.description:
        say(args, f"  {ds.description}")
    if check is not None:
        say(
            args,
            f"  layout check: median |range - layout distance| {check['median_m']:.2f} m over {check['ranges']} ranges",
        )
        for problem in check["problems"]:  # only with --force
            say(args, f"  warning (--force): {problem}")
    return 0
