"""`jaxcal validate FILE [--json] [--quiet]`: check a file that jaxcal wrote.

Contract files (CONTRACT.md section 1) are read and checked in full; a dataset with truth is also
cross-checked against its ranges (`_checks.truth_consistency`): a layout that does not fit the ranges
makes the file `warning` (well-formed, but every evaluation against that truth would be wrong). Sweep
stores, record journals and tune parameter files are checked for their own layout. Exit status: 0 for
`valid` and `warning`, 2 (one line) for an invalid file.
"""

from __future__ import annotations


def add_arguments(p) -> None:
    from jaxcal.commands._common import add_output_flags

    p.add_argument("file", help="a file written by jaxcal (contract HDF5, sweep store, journal, params JSON)")
    add_output_flags(p, "print one JSON object: file, format, status (valid / warning), warnings")


def run(args) -> int:
    import sys

    from jaxcal.commands._checks import truth_consistency
    from jaxcal.commands._common import emit_json, kind_of, load, say
    from jaxcal.commands._files import identify, journal_summary, params_summary, sweep_summary

    kind = identify(args.file)
    warnings: list[str] = []
    extra: dict = {}
    if kind in ("mesh", "trajectory", "result"):
        obj = load(args.file)
        kind = kind_of(obj)
        if kind != "result":
            check = truth_consistency(obj)
            if check is not None:
                warnings += check["problems"]
                extra["layout_median_m"] = check["median_m"]
        what = f"jaxcal {kind} file (version 1)"
    elif kind == "sweep":
        s = sweep_summary(args.file)
        what = f"jaxcal sweep store ({s['done']}/{s['runs']} runs done)"
    elif kind == "journal":
        s = journal_summary(args.file)
        if s["torn_bytes"]:
            warnings.append(f"torn tail of {s['torn_bytes']} bytes dropped (a recording killed mid-write)")
        what = f"jaxcal record journal ({s['frames']} frames)"
    elif kind == "params":
        s = params_summary(args.file)
        what = f"jaxcal parameter file for --method {s['method']} ({len(s['params'])} parameters)"
    else:
        what = "JSON summary written by jaxcal"
    status = "warning" if warnings else "valid"
    emit_json(args, {"file": args.file, "format": kind, "status": status, "warnings": warnings, **extra})
    n = len(warnings)
    say(args, f"{args.file}: valid {what}" + (f", with {n} warning{'s' * (n > 1)}:" if n else ""))
    if not args.json and not args.quiet:
        for w in warnings:
            print(f"  warning: {w}")
    elif warnings and not args.json:
        sys.stderr.write(f"jaxcal: warning: {args.file}: {warnings[0]}\n")
    return 0
