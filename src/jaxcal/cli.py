"""The `jaxcal` command line: orchestration only (io -> core -> io).

Each subcommand lives in `jaxcal.commands.<module>` with two functions: `add_arguments(parser)` (cheap:
no heavy imports at module level, so `jaxcal --help` stays fast) and `run(args) -> int`.

Errors: bad input (`JaxcalError` and its `InputError`, `DataError`, `FormatError`; a missing or unreadable
file) prints one line `jaxcal: error: ...` on stderr and exits 2; an unexpected failure (a plain `ValueError`
from deep inside included: it is a bug, not the user's input) prints one line `jaxcal: internal error: ...`
and exits 1. Set `JAXCAL_DEBUG=1` for the traceback.

Signals: SIGINT (Ctrl-C) and SIGTERM end any command at any moment with one line and exit status 130
(143). They are blocked in every thread and taken by one watcher thread (`signal.sigwait`), which removes
the live temporary files of `jaxcal.io.atomic` and ends the process with `os._exit`. Raising
KeyboardInterrupt in the main thread instead is not safe with JAX: the signal may land while XLA runs or
compiles on its own threads (Python runs its handler only between bytecodes of the main thread, late or,
inside a callback, not at all), and the interpreter then tears down modules while those threads still
run, which crashed with a segmentation fault (exit 139). `record --port` keeps Ctrl-C and SIGTERM as its
clean "stop recording" (see `jaxcal.io.recorder`).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# LAPACK (OpenBLAS) on one thread unless the user says otherwise; set before anything imports NumPy. The mesh
# fits factor small dense matrices (a few hundred rows) thousands of times, where OpenBLAS's worker threads
# cost more than they give and, on a busy machine, spin while they wait for a core: a 301 x 301 Cholesky
# took 104 ms of CPU time instead of 1 ms on 2 cores at load 13 (issue #26). XLA's own threads are not
# affected.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

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

# commands that compile XLA programs: they use the persistent compilation cache (`compile_cache`)
_COMPILING = frozenset({"demo", "calibrate", "simulate", "stats", "evaluate", "gate", "tune", "sweep", "report"})


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


class Terminated(KeyboardInterrupt):
    """SIGTERM in a command that handles interruption itself (`record --port`)."""


def _exit_on_signal(signum: int) -> None:
    """Remove temporaries, flush what was printed, one line, then end the process at once."""
    import signal
    import threading

    from jaxcal.io.atomic import discard_temporaries

    discard_temporaries()

    def flush():
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001 - a closed pipe must not stop the exit
                pass

    t = threading.Thread(target=flush, daemon=True)  # a stream held by a blocked writer: give up after 1 s
    t.start()
    t.join(1.0)
    if signum == signal.SIGINT:
        line, code = b"jaxcal: interrupted\n", 130
    else:
        line, code = b"jaxcal: terminated (SIGTERM)\n", 143
    try:
        os.write(2, line)
    finally:
        os._exit(code)


def _take_signals() -> None:
    """Block SIGINT and SIGTERM in this and every later thread; one watcher thread takes them."""
    import signal
    import threading

    sigs = {signal.SIGINT, signal.SIGTERM}
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        return
    import jaxcal.io.atomic  # noqa: F401 - imported now, not by the watcher while the main thread imports

    signal.pthread_sigmask(signal.SIG_BLOCK, sigs)

    def watch():
        _exit_on_signal(signal.sigwait(sigs))

    threading.Thread(target=watch, name="jaxcal-signals", daemon=True).start()


def _raise_on_sigterm() -> None:
    import signal

    def on_term(signum, frame):
        raise Terminated()

    signal.signal(signal.SIGTERM, on_term)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `jaxcal` console script.

    With `argv` None (the console script, `python -m jaxcal.cli`) the process's signals are taken as the
    module docstring says; an in-process call with a list (a notebook, a test) leaves them alone, and
    Ctrl-C there is a KeyboardInterrupt as usual (exit status 130).
    """
    if argv is None:  # first thing: a signal during the imports below must not print a traceback
        words = sys.argv[1:]
        if words[:1] == ["record"] and any(w == "--port" or w.startswith("--port=") for w in words):
            _raise_on_sigterm()  # the recorder stops cleanly on Ctrl-C / SIGTERM and writes the file
        else:
            _take_signals()
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "_module", None) is None:
        parser.print_help(sys.stderr)
        return 2
    from jaxcal.errors import JaxcalError

    debug = os.environ.get("JAXCAL_DEBUG") not in (None, "", "0")
    if args.command in _COMPILING:
        from jaxcal import compile_cache

        compile_cache.enable()  # programs compiled once per machine (JAXCAL_CACHE_DIR=off: not)
    try:
        rc = args._module.run(args)
        return int(rc or 0)
    except Terminated:
        sys.stderr.write("jaxcal: terminated (SIGTERM)\n")
        return 143
    except KeyboardInterrupt:
        sys.stderr.write("jaxcal: interrupted\n")
        return 130
    except BrokenPipeError:
        return 0
    except (JaxcalError, FileNotFoundError, IsADirectoryError, PermissionError) as e:
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
