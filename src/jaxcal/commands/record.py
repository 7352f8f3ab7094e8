"""`jaxcal record`: record UWB ranges from a serial device (or replay a capture) into a contract file.

    jaxcal record --port PORT --protocol nlink|dwm1001-tlv|dwm1001-shell [--baud B] [--duration S] -o OUT.h5
    jaxcal record --replay CAPTURE.bin|OUT.h5.journal|OUT.h5 [--protocol P] -o OUT.h5 [--json]

    jaxcal record ... --calibrate pgp [--config A0,A1,A2] [--set KEY=VALUE] [--min-epochs 20]

See `jaxcal.io.recorder` for the crash-safety design and the mapping of frames to mesh/trajectory files,
`jaxcal.io.link` for the link faults (device lost and reopened for --reconnect seconds, no data, garbage).

Crash recovery: every decoded frame is in OUT.h5.journal before the next read; after a crash, power loss
or kill, `jaxcal record --replay OUT.h5.journal -o OUT.h5` rebuilds OUT.h5 (and removes the journal). A
`record` onto an existing OUT.h5 or journal refuses and says what is there.

Exit status: 0 done (--duration, end of a replay); 130 Ctrl-C (SIGINT) and 143 SIGTERM, the file complete;
3 the device was lost and did not come back within --reconnect seconds, the file complete up to then;
2 bad input or nothing to write.
`--calibrate pgp` is live (`jaxcal.live`: startup and restart rules, the settled flag): the filter
runs on the epochs as they close, at each flush (replay: each second of frame time), node positions go
to stderr, and OUT.pgp.h5 holds the live result (its track: every epoch's live estimate). The recording
is always written first; a calibration failure is then reported in one line (exit 2).
"""

from __future__ import annotations

PROTOCOL_CHOICES = ("nlink", "dwm1001-tlv", "dwm1001-shell")


def add_arguments(p) -> None:
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--port", help="serial device or pyserial URL (e.g. /dev/ttyUSB0, loop://, a pty path)")
    src.add_argument(
        "--replay",
        metavar="FILE",
        help="decode a raw byte capture, a recorder journal, or a recorded HDF5 file instead",
    )
    p.add_argument(
        "--protocol",
        choices=PROTOCOL_CHOICES,
        help="wire format (required except when replaying a journal or HDF5 file)",
    )
    p.add_argument("-o", "--output", required=True, help="HDF5 file to write (mesh or trajectory)")
    p.add_argument("--baud", type=int, default=None, help="baud rate (default: nlink 921600, dwm1001 115200)")
    p.add_argument("--duration", type=float, default=None, help="seconds to record (default: until Ctrl-C)")
    p.add_argument("--raw-out", default=None, metavar="FILE", help="also write every byte read (a raw capture)")
    p.add_argument(
        "--format",
        dest="fmt",
        choices=("auto", "mesh", "trajectory"),
        default="auto",
        help="output format; auto: trajectory when every range has one tag end, else mesh",
    )
    p.add_argument("--epoch", type=float, default=0.1, help="mesh epoch window [s] (default 0.1)")
    p.add_argument("--self-id", default=None, help="DWM1001: id of the module on the port (default tag/anchor)")
    p.add_argument(
        "--rate",
        type=float,
        default=10.0,
        help="DWM1001: TLV polling rate, and frame rate assumed when replaying a capture [Hz]",
    )
    p.add_argument("--init", action="store_true", help="DWM1001 shell: enter the shell and send `lec` first")
    p.add_argument("--name", default=None, help="dataset name (default: output file stem)")
    p.add_argument(
        "--keep-journal",
        action="store_true",
        help="keep OUT.h5.journal after a clean stop (or after recovering OUT.h5 from it)",
    )
    p.add_argument(
        "--reconnect",
        type=float,
        default=30.0,
        metavar="S",
        help="a lost device (unplugged): reopen the same port for up to S seconds (default 30; "
        "0: end the recording at the loss)",
    )
    p.add_argument(
        "--calibrate",
        default=None,
        metavar="METHOD",
        help="live calibration while recording (pgp: the filter runs on epochs as they close, "
        "positions on stderr; OUT.pgp.h5 at the end); other mesh methods run once at the end",
    )
    p.add_argument(
        "--config",
        default=None,
        metavar="A0,A1,A2",
        help="--calibrate: node ids of the frame, or a configuration name stored in a replayed HDF5 "
        "file (default: the first three by id order that ranged each other)",
    )
    p.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="--calibrate: override a method parameter"
    )
    p.add_argument(
        "--min-epochs",
        type=int,
        default=20,
        help="--calibrate pgp: epochs each frame pair must range before the filter starts (20)",
    )
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
    from jaxcal.commands._common import check_output_path

    out = check_output_path(args.output, [args.replay, args.raw_out]).path
    if args.raw_out:
        check_output_path(args.raw_out, [args.replay])
    kw = {"epoch_s": args.epoch, "fmt": args.fmt, "name": args.name or out.stem, "self_id": args.self_id}
    if (args.config is not None or args.set) and args.calibrate is None:
        raise JaxcalError("--config and --set need --calibrate")
    if args.config is not None and args.calibrate != "pgp":
        raise JaxcalError("--config needs --calibrate pgp (the live frame)")
    params = _overrides(args.set)
    live = None
    if args.calibrate == "pgp":
        from jaxcal.live import LiveCalibrator

        frame = _frame_ids(args.config, args.replay)
        live = LiveCalibrator(params, frame, min_epochs=args.min_epochs, stream=None if args.quiet else sys.stderr)
    on_flush = live.guarded_update if live is not None else None
    if not args.reconnect >= 0:
        raise JaxcalError(f"--reconnect must be >= 0 seconds, got {args.reconnect}")
    t0 = time.monotonic()
    recovering = False
    if args.replay:
        src = Path(args.replay)
        if out.exists() and src.exists() and out.resolve() == src.resolve():
            raise JaxcalError(f"-o {out} is the input: it would be written over; choose another -o")
        recovering = (
            src.name.endswith(".journal") and (src.parent / src.name[: -len(".journal")]).resolve() == out.resolve()
        )
        rec = recorder.replay(args.replay, args.protocol, kw, rate=args.rate, on_flush=on_flush)
        stopped = "end of input"
    else:
        if args.protocol is None:
            raise JaxcalError("--protocol is required with --port")
        from jaxcal.io import capture

        rec = recorder.Recording(args.protocol, **kw)
        status = None if args.quiet else capture.status_printer(sys.stderr)
        stopped = capture.record_serial(
            rec,
            args.port,
            out,
            baud=args.baud,
            duration=args.duration,
            raw_out=args.raw_out,
            rate=args.rate,
            shell_init=args.init,
            status=status,
            on_flush=on_flush,
            reconnect_s=args.reconnect,
        )
    if live is not None:
        live.guarded_update(rec, final=True)  # the last epochs; sets the frame written to the file
    written = rec.write(out)  # the recording first: a calibration failure never loses it
    if written and not args.replay:
        capture.finish_journal(rec, args.keep_journal)
    elif not written and rec.journal is not None and rec.journal.frames == 0:
        rec.journal.path.unlink(missing_ok=True)  # nothing to recover: do not block the next recording
        rec.journal = None
    if written and recovering and not args.keep_journal:
        Path(args.replay).unlink()
    summary = rec.summary()
    summary.update(output=str(out) if written else None, stopped=stopped, seconds=time.monotonic() - t0)
    if rec.link is not None:
        summary["link"] = rec.link
    calib_error = None
    if written and args.calibrate:
        try:
            summary["calibration"] = _calibrate(out, args.calibrate, live, params, args.config)
        except Exception as e:  # noqa: BLE001 - any failure: one line, the recording is already safe
            calib_error = " ".join(str(e).split()) or type(e).__name__
            summary["calibration"] = {"method": args.calibrate, "error": calib_error}
    if args.json:
        print_json(summary)
    counts = (
        f"{summary['frames']} frames, {summary['ranges']} ranges, {summary['checksum_failures']} checksum "
        f"failures, {summary['bytes_skipped']} bytes skipped"
    )
    code = {"sigint": 130, "sigterm": 143, "device lost": 3}.get(stopped, 0)
    why = {
        "sigint": "interrupted (Ctrl-C)",
        "sigterm": "terminated (SIGTERM)",
        "device lost": "the device was lost and did not come back",
    }.get(stopped)
    if stopped == "error":
        detail = (rec.link or {}).get("error") or "the reader failed"
        where = f"; {out} holds everything received" if written else ""
        raise JaxcalError(f"recording stopped: {detail}{where}")
    if not written:
        where = f"; the raw frames are in {out}.journal" if rec.journal is not None else ""
        msg = (
            f"no dataset written: {summary['ranges']} ranges between {summary['nodes']} nodes "
            f"({counts}) is not enough for a {rec.kind() or 'mesh'} file{where}"
        )
        if why is None:
            raise JaxcalError(msg)
        sys.stderr.write(f"jaxcal: {why}: {msg}\n")
        return code
    if why is not None:
        sys.stderr.write(f"jaxcal: {why}: recording complete, {counts} -> {out}\n")
    elif recovering:
        gone = "" if args.keep_journal else "; journal removed"
        sys.stderr.write(f"jaxcal: recovered {counts} from {args.replay} -> {out}{gone}\n")
    elif not args.json and (args.replay or args.quiet):
        sys.stderr.write(f"{counts} -> {out}\n")
    if calib_error is not None:
        raise JaxcalError(f"recording written to {out}, but --calibrate {args.calibrate} failed: {calib_error}")
    return code


def _frame_ids(text: str | None, replay: str | None):
    """`--config` (the shared parser: three node ids, or a configuration stored in a replayed file)."""
    from jaxcal.commands._common import parse_config, resolve_config
    from jaxcal.errors import JaxcalError

    cfg = parse_config(text)
    if cfg is None or isinstance(cfg, tuple):
        return cfg
    if replay and str(replay).endswith((".h5", ".hdf5")):
        from jaxcal.commands._common import load

        ds, name = resolve_config(load(replay, ("mesh",)), cfg)
        return tuple(ds.node_ids[i] for i in ds.config(name))
    raise JaxcalError(f"--config {cfg}: a live recording has no stored configurations; give three node ids A0,A1,A2")


def _overrides(items) -> dict:
    from jaxcal.errors import JaxcalError

    out = {}
    for item in items:
        if "=" not in item:
            raise JaxcalError(f"--set wants KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def _calibrate(path, method: str, live, params: dict, config: str | None) -> dict:
    """Write OUT.METHOD.h5: the live filter's result (pgp), else one run of the method on the file."""
    from jaxcal.commands._common import load
    from jaxcal.errors import JaxcalError
    from jaxcal.io import hdf5
    from jaxcal.methods import calibrate

    ds = load(str(path), ("mesh",))
    if not hasattr(ds, "node_ids"):
        raise JaxcalError(f"--calibrate {method}: needs a mesh recording, this one is a trajectory file")
    if live is not None:
        if live.error is not None:
            raise JaxcalError(live.error)
        result = live.result(ds)
    else:
        result = calibrate(ds, method, params or None)
    res_path = str(path)[: -len(".h5")] if str(path).endswith(".h5") else str(path)
    res_path += f".{method}.h5"
    hdf5.write(res_path, result)
    info = {"method": method, "output": res_path, "ids": list(result.ids), "position": result.position}
    if live is not None:
        info.update(live=True, frame=list(live.frame), restarts=live.restarts, settled=live.settled_at)
    return info
