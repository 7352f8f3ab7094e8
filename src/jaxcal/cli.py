"""The `jaxcal` command line: orchestration only (io -> core -> io).

Each subcommand lives in `jaxcal.commands.<module>` with two functions: `add_arguments(parser)` (cheap:
no heavy imports at module level, so `jaxcal --help` stays fast) and `run(args) -> int`.

Errors: bad input (`JaxcalError`, a missing file, a bad value) prints one line `jaxcal: error: ...` on
stderr and exits 2; an unexpected failure prints one line and exits 1. Set `JAXCAL_DEBUG=1` for the
traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# name -> (module under jaxcal.commands, one-line help). Order is the order of `jaxcal --help`.
COMMANDS: dict[str, tuple[str, str]] = {
    "import": ("importer", "convert a recording (dwm1001-autocal, hymn, cuhksz, hanyang, csv) to a jaxcal file"),
    "demo": ("demo", "run the paper's evaluation on the embedded simulated dataset"),
    "info": ("info", "summarise a jaxcal file"),
    "validate": ("validate", "check a file against the HDF5 contract"),
    "calibrate": ("calibrate", "estimate node or anchor positions (--method cf, pgp, gp, ...)"),
    "record": ("record", "record ranges from a serial UWB device (NLink, DWM1001) or replay a capture"),
    "simulate": ("simulate", "simulate a mesh or trajectory dataset (--scenario torgau, campus, ...)"),
    "stats": ("stats", "ranging error statistics by LOS / NLOS (Table I)"),
    "evaluate": ("evaluate", "compare a result with the ground truth of a dataset"),
    "gate": ("gate", "UWB range-zone gated place recognition (--simulate DIR for a demo yard)"),
    "tune": (
        "tune",
        "fit sigma_r, sigma_v, tau (and nlos_weight, nlos_mean_m with --set range_model=mixture)"
        " of the PGP filter by gradient (truth or evidence)",
    ),
    "sweep": ("sweep", "run a parameter x scenario x seed grid of the PGP filter (vmapped, sharded, resumable)"),
    "report": ("report", "write figures and an index.html of results against the truth, and of sweeps"),
}


class _Parser(argparse.ArgumentParser):
    """argparse that reports usage errors as one line and exit status 2."""

    def error(self, message: str):  # noqa: D401
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    from jaxcal import __version__

    parser = _Parser(prog="jaxcal", description="UWB anchor self-calibration (mesh and trajectory methods).")
    parser.add_argument("--version", action="version", version=f"jaxcal {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name, (module, help_text) in COMMANDS.items():
        mod = importlib.import_module(f"jaxcal.commands.{module}")
        p = sub.add_parser(name, help=help_text, description=help_text)
        mod.add_arguments(p)
        p.set_defaults(_module=mod)
    return parser


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return " ".join(text.split())


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `jaxcal` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "_module", None) is None:
        parser.print_help(sys.stderr)
        return 2
    from jaxcal.errors import JaxcalError

    debug = os.environ.get("JAXCAL_DEBUG") not in (None, "", "0")
    try:
        rc = args._module.run(args)
        return int(rc or 0)
    except KeyboardInterrupt:
        sys.stderr.write("jaxcal: interrupted\n")
        return 130
    except BrokenPipeError:
        return 0
    except (JaxcalError, FileNotFoundError, IsADirectoryError, PermissionError, ValueError) as e:
        if debug:
            raise
        if isinstance(e, FileNotFoundError) and e.filename:
            msg = f"{e.filename}: no such file"
        else:
            msg = _one_line(e)
        sys.stderr.write(f"jaxcal: error: {msg}\n")
        return 2
    except Exception as e:  # an unexpected failure: still one line, never a traceback
        if debug:
            raise
        sys.stderr.write(
            f"jaxcal: internal error: {type(e).__name__}: {_one_line(e)} (set JAXCAL_DEBUG=1 for details)\n"
        )
        return 1


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
