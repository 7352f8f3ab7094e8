"""`jaxcal record`: record UWB ranges from a serial device (or replay a capture) into a contract file.

    jaxcal record --port PORT --protocol nlink|dwm1001-tlv|dwm1001-shell [--baud B] [--duration S] -o OUT.h5
    jaxcal record --replay CAPTURE.bin|OUT.h5.journal|OUT.h5 [--protocol P] -o OUT.h5 [--json]

See `jaxcal.io.recorder` for the crash-safety design and the mapping of frames to mesh/trajectory files.
"""

from __future__ import annotations

PROTOCOL_CHOICES = ("nlink", "dwm1001-tlv", "dwm1001-shell")


def add_arguments(p) -> None:
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--port", help="serial device or pyserial URL (e.g. /dev/ttyUSB0, loop://, a pty path)")
    src.add_argument("--replay", metavar="FILE",
                     help="decode a raw byte capture, a recorder journal, or a recorded HDF5 file instead")
    p.add_argument("--protocol", choices=PROTOCOL_CHOICES,
                   help="wire format (required except when replaying a journal or HDF5 file)")
    p.add_argument("-o", "--output", required=True, help="HDF5 file to write (mesh or trajectory)")
    p.add_argument("--baud", type=int, default=None, help="baud rate (default: nlink 921600, dwm1001 115200)")
    p.add_argument("--duration", type=float, default=None, help="seconds to record (default: until Ctrl-C)")
    p.add_argument("--raw-out", default=None, metavar="FILE", help="also write every byte read (a raw capture)")
    p.add_argument("--format", dest="fmt", choices=("auto", "mesh", "trajectory"), default="auto",
                   help="output format; auto: trajectory when every range has one tag end, else mesh")
    p.add_argument("--epoch", type=float, default=0.1, help="mesh epoch window [s] (default 0.1)")
    p.add_argument("--self-id", default=None, help="DWM1001: id of the module on the port (default tag/anchor)")
    p.add_argument("--rate", type=float, default=10.0,
                   help="DWM1001: TLV polling rate, and frame rate assumed when replaying a capture [Hz]")
    p.add_argument("--init", action="store_true", help="DWM1001 shell: enter the shell and send `lec` first")
    p.add_argument("--name", default=None, help="dataset name (default: output file stem)")
    p.add_argument("--keep-journal", action="store_true", help="keep OUT.h5.journal after a clean stop")
    p.add_argument("--calibrate", default=None, metavar="METHOD",
                   help="calibrate the recorded mesh with a registered mesh method (e.g. pgp) when done")
    p.add_argument("--quiet", action="store_true", help="no status line")
    p.add_argument("--json", action="store_true", help="print one JSON object with the counters at the end")


def _check_calibrate(method: str | None) -> None:
    if method is None:
        return
    from jaxcal.errors import JaxcalError
    from jaxcal.methods import MESH_METHODS

    if method not in MESH_METHODS:
        known = ", ".join(sorted(MESH_METHODS)) or "none"
        raise JaxcalError(
            f"--calibrate {method}: no mesh method {method!r} is registered yet (known: {known}); "
            f"record without --calibrate and run `jaxcal calibrate` on the file later"
        )


def run(args) -> int:
    import sys
    import time
    from pathlib import Path

    from jaxcal.commands._common import print_json
    from jaxcal.errors import JaxcalError
    from jaxcal.io import recorder

    _check_calibrate(args.calibrate)
    if args.duration is not None and not args.duration > 0:
        raise JaxcalError(f"--duration must be positive, got {args.duration}")
    if not args.rate > 0:
        raise JaxcalError(f"--rate must be positive, got {args.rate}")
    out = Path(args.output)
    kw = {"epoch_s": args.epoch, "fmt": args.fmt, "name": args.name or out.stem, "self_id": args.self_id}
    t0 = time.monotonic()
    if args.replay:
        rec = recorder.replay(args.replay, args.protocol, kw, rate=args.rate)
        stopped = "end of input"
    else:
        if args.protocol is None:
            raise JaxcalError("--protocol is required with --port")
        rec = recorder.Recording(args.protocol, **kw)
        status = None if args.quiet else recorder.status_printer(sys.stderr)
        stopped = recorder.record_serial(
            rec, args.port, out, baud=args.baud, duration=args.duration, raw_out=args.raw_out,
            rate=args.rate, shell_init=args.init, status=status,
        )
    written = rec.write(out)
    if written:
        recorder.finish_journal(rec, args.keep_journal)
    summary = rec.summary()
    summary.update(output=str(out) if written else None, stopped=stopped, seconds=time.monotonic() - t0)
    calibration = None
    if written and args.calibrate:
        calibration = _calibrate(out, args.calibrate)
        summary["calibration"] = calibration
    if args.json:
        print_json(summary)
    elif written and (args.replay or args.quiet):
        sys.stderr.write(
            f"{summary['frames']} frames, {summary['ranges']} ranges, {summary['checksum_failures']} checksum "
            f"failures, {summary['bytes_skipped']} bytes skipped -> {out}\n"
        )
    if not written:
        where = f"; the raw frames are in {out}.journal" if rec.journal is not None else ""
        raise JaxcalError(
            f"no dataset written: {summary['ranges']} ranges between {summary['nodes']} nodes "
            f"({summary['frames']} frames, {summary['checksum_failures']} checksum failures, "
            f"{summary['bytes_skipped']} bytes skipped) is not enough for a {rec.kind() or 'mesh'} file{where}"
        )
    return 0


def _calibrate(path, method: str) -> dict:
    """Hook for issue 8 item 4: for now, calibrate the finished recording once (not live)."""
    from jaxcal.commands._common import load
    from jaxcal.errors import JaxcalError
    from jaxcal.io import hdf5
    from jaxcal.methods import calibrate

    ds = load(str(path), ("mesh",))
    if not hasattr(ds, "node_ids"):
        raise JaxcalError(f"--calibrate {method}: needs a mesh recording")
    result = calibrate(ds, method)
    res_path = str(path)[: -len(".h5")] if str(path).endswith(".h5") else str(path)
    res_path += f".{method}.h5"
    hdf5.write(res_path, result)
    return {"method": method, "output": res_path, "ids": list(result.ids), "position": result.position}
