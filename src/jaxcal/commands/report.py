"""`jaxcal report RESULT.h5 [RESULT2.h5 ...] --truth DATASET.h5 -o DIR [--posteriors SPEC]`.

Writes the papers' figures as PNG files and an `index.html` that shows them with their numbers (see
`jaxcal.report`). Results are grouped by (method, configuration). Posterior grids (Fig. 6 style) are
recomputed by re-running PGP on the first epochs of the dataset: `--posteriors auto` (default), `none`, or
`NODE,NODE@EPOCH,EPOCH` (e.g. `D5B4,9911@5,20,100`).
"""

from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("results", nargs="+", metavar="RESULT.h5", help="result files of one dataset")
    p.add_argument(
        "--truth", required=True, metavar="DATASET.h5", help="the dataset with ground truth"
    )
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="folder to write (created)")
    p.add_argument(
        "--posteriors",
        default="auto",
        help="posterior grids: auto (default), none, or NODE,...@EPOCH,... (re-runs PGP on those epochs)",
    )
    p.add_argument(
        "--label",
        action="append",
        default=None,
        metavar="TEXT",
        help="label of each result in order (repeat; default method/configuration)",
    )
    p.add_argument(
        "--json", action="store_true", help="print the report's numbers as one JSON object"
    )


def run(args) -> int:
    import json
    import time

    from jaxcal.commands._common import load, print_json
    from jaxcal.report import parse_posteriors, write_report

    t0 = time.perf_counter()
    spec = parse_posteriors(args.posteriors)
    truth = load(args.truth, ("mesh", "trajectory"))
    results = [load(path, ("result",)) for path in args.results]
    index = write_report(results, truth, args.output, labels=args.label, posteriors=spec)
    seconds = time.perf_counter() - t0
    if args.json:
        numbers = json.loads((index.parent / "report.json").read_text())
        print_json({"index": str(index), "seconds": seconds, **numbers})
    else:
        print(f"report in {index} ({seconds:.1f} s)")
    return 0
