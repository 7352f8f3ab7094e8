"""`jaxcal import FORMAT SRC... -o OUT [--name NAME] [--json]`: convert a recording to a jaxcal file.

Forms (scripts rely on them):
    jaxcal import dwm1001-autocal SCENARIO_DIR NODES_CFG.yaml -o OUT
    jaxcal import hymn DATASET_ROOT -o OUT          (the folder holding data/)
    jaxcal import cuhksz UWB.csv MOCAP.csv -o OUT
    jaxcal import hanyang RUN_DIR -o OUT
    jaxcal import csv FILE -o OUT
"""

from __future__ import annotations

_FORMATS = "dwm1001-autocal, hymn, cuhksz, hanyang, csv"


def add_arguments(p) -> None:
    p.add_argument("format", metavar="FORMAT", help=f"recording format: {_FORMATS}")
    p.add_argument("sources", metavar="SRC", nargs="+", help="source file(s) or folder(s) of the recording")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="jaxcal HDF5 file to write")
    p.add_argument("--name", default=None, help="dataset name (default: derived from the source)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")


def run(args) -> int:
    import time

    from jaxcal.commands._common import kind_of, print_json
    from jaxcal.io import hdf5
    from jaxcal.io.importers import import_recording

    t0 = time.perf_counter()
    ds = import_recording(args.format, *args.sources, name=args.name)
    out = hdf5.write(args.output, ds)
    kind = kind_of(ds)
    summary = {"file": str(out), "format": kind, "name": ds.name, "importer": args.format}
    if kind == "mesh":
        import numpy as np

        summary.update(nodes=ds.n_nodes, epochs=ds.n_epochs, ranges=int(np.isfinite(ds.range).sum()))
    else:
        summary.update(anchors=ds.n_anchors, tags=len(ds.tag_ids), poses=int(ds.pose_time.shape[0]),
                       ranges=ds.n_ranges)
    summary["description"] = ds.description
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    if args.json:
        print_json(summary)
        return 0
    counts = ", ".join(f"{k} {summary[k]}" for k in ("nodes", "epochs", "anchors", "tags", "poses", "ranges")
                       if k in summary)
    print(f"wrote {out}: {kind} '{ds.name}' ({counts}) in {summary['seconds']:.2f} s")
    if ds.description:
        print(f"  {ds.description}")
    return 0
