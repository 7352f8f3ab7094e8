"""The live loop of ``jaxcal record --port``: checks, the journal, the reader thread, snapshots, status.

`record_serial` opens the port first (a bad port fails before any file is made), creates the journal
(`jaxcal.io.journal`), starts the reader thread (`jaxcal.io.link`: it decodes and journals every frame
before reading again), and only then imports h5py / JAX for the snapshots, on a thread of its own, so
that neither a frame nor a fault line waits for that import. The main thread moves the decoded frames
into the `Recording`, fsyncs the journal and the raw
capture every ``flush_s``, rewrites the atomic HDF5 snapshot, runs ``on_flush`` (the live filter),
prints the status line and one line per link fault (see `jaxcal.io.link`).

Stops: ``--duration``, SIGINT (Ctrl-C) and SIGTERM (handled as flags: the loop ends, the reader drains,
the final snapshot is written; a second signal interrupts that last write, which leaves the journal),
the device not coming back within ``reconnect_s``, or a failure of the reader (e.g. a full disk).
"""

from __future__ import annotations

import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from jaxcal.errors import JaxcalError
from jaxcal.io.journal import JournalWriter, describe_journal, open_exclusive
from jaxcal.io.link import RECONNECT_S, STALL_S, SerialLink, open_port
from jaxcal.io.recorder import DEFAULT_BAUD, Recording

__all__ = [
    "record_serial",
    "check_outputs",
    "journal_path",
    "finish_journal",
    "status_printer",
    "warner",
    "recover_command",
]


def journal_path(out: str | os.PathLike) -> Path:
    return Path(str(out) + ".journal")


def recover_command(out: str | os.PathLike) -> str:
    """The one command that rebuilds ``OUT.h5`` from its journal."""
    return f"jaxcal record --replay {journal_path(out)} -o {out}"


def check_outputs(out: str | os.PathLike, raw_out: str | os.PathLike | None = None) -> None:
    """Before a port is opened: the folder exists, and no recording would be written over (an
    interrupted one is described with its recovery command)."""
    out = Path(out)
    if not out.parent.exists():
        raise JaxcalError(f"{out}: folder {out.parent} does not exist")
    j = journal_path(out)
    if j.exists():
        raise JaxcalError(
            f"{j}: an interrupted recording is here ({describe_journal(j)}); nothing was overwritten: "
            f"recover it with `{recover_command(out)}` or move it away"
        )
    if out.exists():
        raise JaxcalError(f"{out} exists (a previous recording?): not overwritten; choose another -o or move it away")
    if raw_out is not None and Path(raw_out).exists():
        raise JaxcalError(f"--raw-out {raw_out} exists: not overwritten; choose another name or move it away")


def warner(stream=sys.stderr) -> Callable[[str], None]:
    """One ``jaxcal: warning: ...`` line per fault (clearing a status line being rewritten on a terminal)."""
    tty = getattr(stream, "isatty", lambda: False)()

    def warn(line: str) -> None:
        stream.write(("\r\x1b[K" if tty else "") + f"jaxcal: warning: {line}\n")
        stream.flush()

    return warn


def record_serial(
    rec: Recording,
    port: str,
    out: str | os.PathLike,
    baud: int | None = None,
    duration: float | None = None,
    raw_out: str | os.PathLike | None = None,
    flush_s: float = 1.0,
    rate: float = 10.0,
    shell_init: bool = False,
    status: Callable[[dict, float, bool], None] | None = None,
    on_flush: Callable[[Recording], None] | None = None,
    reconnect_s: float = RECONNECT_S,
    stall_s: float = STALL_S,
    warn: Callable[[str], None] | None = None,
) -> str:
    """Record `port` into `out` (journal + snapshots) until a stop; see the module docstring.

    Args:
        rec: the `Recording` to fill (its protocol selects the reader).
        port: a device path or any pyserial URL (``loop://``, ``socket://``, a pty path).
        out: the HDF5 file; the journal is ``out + ".journal"``. Neither may exist.
        baud: baud rate (default per protocol: NLink 921600, DWM1001 115200).
        duration: seconds to record (None: until stopped).
        raw_out: also write every byte read to this new file (a raw capture for `replay`).
        flush_s: fsync and snapshot period [s].
        rate: DWM1001 TLV polling rate [Hz].
        shell_init: DWM1001 shell: send ``\\r\\r``, wait 1.1 s, send ``lec\\r`` (lec toggles the stream).
        status: callback(summary, elapsed_s, final) for the status line.
        on_flush: called with the recording after each flush (live calibration); its exceptions are the
            caller's to contain.
        reconnect_s: how long to try reopening a lost device at the same path (0: stop at the loss).
        stall_s: silence reported as "no data" [s].
        warn: where fault lines go (default: ``jaxcal: warning: ...`` on stderr).

    Returns:
        Why it stopped: ``"duration"``, ``"sigint"``, ``"sigterm"``, ``"device lost"`` or ``"error"``
        (the reader failed: ``rec.link["error"]``). ``rec.link`` holds the link counters and fault lines.
    """
    out = Path(out)
    check_outputs(out, raw_out)
    warn = warn or warner(sys.stderr)
    baud = baud or DEFAULT_BAUD[rec.protocol]
    try:
        ser = open_port(port, baud)
    except Exception as e:  # noqa: BLE001 - SerialException, ValueError, OSError: one line
        raise JaxcalError(f"{port}: cannot open serial port ({' '.join(str(e).split())})") from None
    raw_fd = None
    try:
        raw_fd = open_exclusive(raw_out) if raw_out else None
        rec.journal = JournalWriter(
            journal_path(out),
            {
                "protocol": rec.protocol,
                "self_id": rec.self_id or "",
                "time_source": "host",
                "start_wall_time": rec.start_wall_time,
                "port": port,
                "baud": baud,
            },
        )
    except BaseException:
        ser.close()
        if raw_fd is not None:
            os.close(raw_fd)
        raise
    t0 = time.monotonic()
    link = SerialLink(
        ser,
        port,
        baud,
        rec.protocol,
        rec.decoder,
        rec.journal,
        raw_fd,
        t0,
        rate=rate,
        shell_init=shell_init,
        reconnect_s=reconnect_s,
        stall_s=stall_s,
    )
    stop: dict = {"why": None}
    old: dict = {}

    def on_signal(signum, frame):
        stop["why"] = "sigint" if signum == signal.SIGINT else "sigterm"
        for s, h in old.items():  # a second signal interrupts the final write (the journal stays)
            signal.signal(s, h)

    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            old[s] = signal.signal(s, on_signal)
    link.start()
    # h5py and JAX (via jaxcal.data) take a second or more to import: on a thread of their own, so that
    # neither the reader nor the fault checks wait for them; the first snapshot waits for them
    imports = threading.Thread(target=_snapshot_imports, name="jaxcal-imports", daemon=True)
    imports.start()
    last_flush = last_snap = last_status = t0
    snap_cost = 0.0
    try:
        while stop["why"] is None:
            try:
                rec.add(*link.frames.get(timeout=0.05))
            except queue.Empty:
                pass
            for item in link.drain():
                rec.add(*item)
            now = time.monotonic()
            _say_events(link, warn)
            if link.ended is not None and not link.alive:
                stop["why"] = link.ended
                break
            for line in link.check(now):
                warn(line)
            if duration is not None and now - t0 >= duration:
                stop["why"] = "duration"
                break
            if now - last_flush >= flush_s:
                rec.journal.sync()
                if raw_fd is not None:
                    os.fsync(raw_fd)
                last_flush = now
                # the snapshot is rewritten whole: keep it under ~10 % of the time for big recordings
                if not imports.is_alive() and now - last_snap >= max(flush_s, min(10 * snap_cost, 60.0)):
                    s0 = time.monotonic()
                    if rec.write(out):
                        snap_cost = time.monotonic() - s0
                    last_snap = now
                if on_flush is not None and not imports.is_alive():  # never two threads importing JAX
                    on_flush(rec)
            if status is not None and now - last_status >= 0.5:
                status(dict(rec.summary(), link=link.state_text(now)), now - t0, False)
                last_status = now
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        link.stop()
        imports.join()  # the caller writes the final snapshot next
        for item in link.drain():
            rec.add(*item)
        _say_events(link, warn)
        rec.journal.close()
        if raw_fd is not None:
            os.fsync(raw_fd)
            os.close(raw_fd)
        rec.link = {
            "faults": link.faults,
            "losses": link.losses,
            "reconnects": link.reconnects,
            "bytes_read": link.bytes_rx,
            "error": link.error,
        }
    if status is not None:
        status(dict(rec.summary(), link=link.state_text(time.monotonic())), time.monotonic() - t0, True)
    return stop["why"] or "duration"


def _snapshot_imports() -> None:
    import h5py  # noqa: F401

    import jaxcal.io.hdf5  # noqa: F401


def _say_events(link: SerialLink, warn) -> None:
    while True:
        try:
            warn(link.events.get_nowait())
        except queue.Empty:
            return


def finish_journal(rec: Recording, keep: bool) -> None:
    """After the final snapshot was written: remove the journal unless `keep`."""
    if rec.journal is not None and not keep:
        try:
            rec.journal.path.unlink()
        except FileNotFoundError:
            pass


def status_printer(stream=sys.stderr) -> Callable[[dict, float, bool], None]:
    """A status-line callback: rewrites one line on a terminal, prints a line every 5 s otherwise.

    The line: elapsed time, frames (rate), ranges (rate), checksum failures, bytes skipped, nodes seen,
    and the link state when it is not ``ok`` (``no data N s``, ``garbage (baud?)``, ``lost N s``)."""
    tty = stream.isatty()
    state = {"t": 0.0, "frames": 0, "ranges": 0, "printed": -1e9}

    def show(s: dict, elapsed: float, final: bool) -> None:
        dt = max(elapsed - state["t"], 1e-9)
        fps = (s["frames"] - state["frames"]) / dt
        rps = (s["ranges"] - state["ranges"]) / dt
        state.update(t=elapsed, frames=s["frames"], ranges=s["ranges"])
        line = (
            f"{elapsed:7.1f} s  frames {s['frames']} ({fps:.1f}/s)  ranges {s['ranges']} ({rps:.1f}/s)  "
            f"checksum failures {s['checksum_failures']}  skipped {s['bytes_skipped']} B  nodes {s['nodes']}"
        )
        if s.get("link", "ok") != "ok":
            line += f"  link: {s['link']}"
        if tty:
            stream.write("\r" + line + ("\n" if final else "\x1b[K"))
        elif final or elapsed - state["printed"] >= 5.0:
            stream.write(line + "\n")
            state["printed"] = elapsed
        stream.flush()

    return show
