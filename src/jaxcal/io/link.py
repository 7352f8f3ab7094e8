"""The device side of ``jaxcal record --port``: one thread that reads the serial port, decodes, and
hands every frame to the journal before it reads again; the faults of a real link, and reconnection.

Why a thread of its own: the main thread writes HDF5 snapshots, runs the live filter and prints the
status line, which can take longer than a serial driver's buffer lasts at 921600 baud. The reader
thread never waits for them: per read it (1) writes the bytes to the ``--raw-out`` capture (`os.write`,
no user-space buffer), (2) feeds the decoder, (3) writes the completed frames to the journal in one
`os.write`, and only then (4) queues them for the main thread and reads again. A SIGKILL therefore loses
at most the bytes of the read being decoded at that instant, i.e. the frame being decoded (a read can
hold several frames when the reader fell behind; it holds one or a part of one at the nominal rate).

Faults (one line each, reported by the main thread through `events` and `check`):

* **device lost** (a read or write fails, e.g. a USB adapter unplugged; the partial frame is dropped):
  the port is reopened at the same path every 0.25 s for up to ``reconnect_s`` seconds (DWM1001 shell:
  ``--init`` is sent again, since a module that was reset starts in TLV mode); a device that drops again
  within 5 s of coming back does not restart that clock. Past it the link ends (``ended``) and the
  recording is closed with everything received.
* **no data** for ``stall_s`` seconds while the port is open (module off, output disabled, TLV requests
  unanswered); a second line when data comes back.
* **garbage**: at least 256 bytes and 1 s since the last valid frame: a wrong baud rate or protocol; a
  second line when valid frames come back. Frames before and after are kept.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable

from jaxcal.io.journal import JournalWriter, write_all

__all__ = ["SerialLink", "open_port", "STALL_S", "RECONNECT_S"]

STALL_S = 2.0
RECONNECT_S = 30.0
GARBAGE_S = 1.0
GARBAGE_BYTES = 256
# the DWM1001 shell prints a banner, echoes and prompts (a few hundred bytes of text) before its first
# location line: until the first valid frame after (re)opening, the garbage rule waits this much longer
SHELL_START_FACTOR = 4
STABLE_S = 5.0
RETRY_S = 0.25
HINTS = {
    "nlink": "powered, and an output frame chosen in NAssistant?",
    "dwm1001-tlv": "the module does not answer dwm_loc_get: in shell mode? "
    "(power-cycle it, or use the shell with --init)",
    "dwm1001-shell": "is `lec` streaming? (--init starts it; lec toggles)",
}


class _PortError(Exception):
    """A read, write or control call on the port failed: the device is treated as lost."""


def open_port(port: str, baud: int):
    """pyserial port (any URL pyserial knows) with a 50 ms read timeout, locked (flock) so that a second
    recorder on the same port fails instead of taking half of the bytes."""
    import serial

    return serial.serial_for_url(port, baudrate=baud, timeout=0.05, exclusive=True)


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


class SerialLink:
    """Reader thread of a live recording (see the module docstring).

    Args:
        ser: the open port (opened by the caller, so that a bad port fails before any file is made).
        port: its path or URL (reopened on a fault). baud: baud rate. protocol: wire format.
        decoder: the recording's incremental decoder (used by this thread only).
        journal: the recording's journal; raw_fd: descriptor of the ``--raw-out`` capture or None.
        t0: host monotonic time of the recording's start (frame times are relative to it).
        rate: DWM1001 TLV polling rate [Hz]. shell_init: send ``\\r\\r``, wait 1.1 s, send ``lec\\r``.
        reconnect_s: how long to try reopening a lost device (0: end at the first loss).
        stall_s: silence that is reported as "no data".
        opener: ``(port, baud) -> serial`` (tests).
    """

    def __init__(
        self,
        ser,
        port: str,
        baud: int,
        protocol: str,
        decoder,
        journal: JournalWriter,
        raw_fd: int | None,
        t0: float,
        rate: float = 10.0,
        shell_init: bool = False,
        reconnect_s: float = RECONNECT_S,
        stall_s: float = STALL_S,
        opener: Callable = open_port,
    ) -> None:
        self.ser, self.port, self.baud, self.protocol = ser, port, baud, protocol
        self.decoder, self.journal, self.raw_fd, self.t0 = decoder, journal, raw_fd, t0
        self.rate, self.shell_init, self.reconnect_s, self.stall_s = rate, shell_init, reconnect_s, stall_s
        self.opener = opener
        self.frames: queue.Queue = queue.Queue()  # (list[Frame], time_s)
        self.events: queue.Queue = queue.Queue()  # one-line messages from the thread
        self.state = "ok"  # "ok" or "lost"
        self.ended: str | None = None  # why the thread ended on its own ("device lost", "error")
        self.error: str | None = None
        self.last_rx = t0  # host monotonic time of the last bytes received
        self.last_gap = 0.0
        self.bytes_rx = 0
        self.last_frame = t0  # host monotonic time of the last valid frame
        self.bytes_since_frame = 0
        self._framed = False  # a valid frame since the port was (re)opened
        self.reads = 0
        self.losses = 0
        self.reconnects = 0
        self.faults: list[str] = []  # every fault line, in order (for --json)
        self._stop = threading.Event()
        self._next_poll = t0
        self._flush_next = True  # TLV: flush stale input before the first request
        self._up_since = t0
        self._lost_since: float | None = None
        self._why_closed = "not open"
        # main-thread fault checks
        self._stalled = False
        self._garbage = False
        self._thread = threading.Thread(target=self._run, name="jaxcal-serial-link", daemon=True)

    # ------------------------------------------------------------------------------ thread control
    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Ask the thread to end after its current read and wait for it (it closes the port)."""
        self._stop.set()
        self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def drain(self) -> list[tuple[list, float]]:
        """Every queued (frames, time) item."""
        out = []
        while True:
            try:
                out.append(self.frames.get_nowait())
            except queue.Empty:
                return out

    # ------------------------------------------------------------------------------ the thread
    def _port(self, fn, *args):
        import termios

        import serial

        try:
            return fn(*args)
        except (serial.SerialException, OSError, termios.error, TypeError, AttributeError) as e:
            # TypeError / AttributeError: pyserial calls on a port whose descriptor vanished
            raise _PortError(_one_line(e)) from None

    def _run(self) -> None:
        try:
            if self.shell_init:
                self._init_shell_or_lose()
            while not self._stop.is_set():
                try:
                    if self.ser is None:
                        raise _PortError(self._why_closed)
                    if self.protocol == "dwm1001-tlv":
                        self._poll()
                    else:
                        self._read()
                except _PortError as e:
                    if not self._reconnect(str(e)):
                        break
            self._close_decoder()
        except Exception as e:  # noqa: BLE001 - e.g. the disk is full: the main thread reports it
            self.error = f"{type(e).__name__}: {_one_line(e)}"  # the caller's one error line
            self.ended = "error"
        finally:
            if self.ser is not None:
                try:
                    self.ser.close()
                except Exception:  # noqa: BLE001 - closing a vanished port must not hide the recording
                    pass

    def _got(self, data: bytes, now: float) -> int:
        """Raw capture, decode, journal, queue: in that order, before the next read."""
        if self.raw_fd is not None:
            write_all(self.raw_fd, data)
        self.bytes_rx += len(data)
        self.reads += 1
        self.last_gap = max(self.last_gap, now - self.last_rx)  # the longest silence since `check` reset it
        self.last_rx = now
        self.bytes_since_frame += len(data)
        return self._emit(self.decoder.feed(data), now - self.t0)

    def _emit(self, frames: list, t: float) -> int:
        if frames:
            self.journal.extend([f.raw for f in frames], t)
            self.frames.put((frames, t))
            self.last_frame = time.monotonic()
            self.bytes_since_frame = 0
            self._framed = True
        return len(frames)

    def _read(self) -> None:
        ser = self.ser
        data = self._port(lambda: ser.read(max(1, ser.in_waiting)))
        if data:
            self._got(data, time.monotonic())

    def _poll(self) -> None:
        """One dwm_loc_get request and its answer. The request goes out in one write (the module
        delimits requests by idle time). Stale bytes are flushed only before the first request (and
        after a reconnect): a late answer is then decoded when it arrives (the stream decoder resyncs
        on ``40 01``) instead of being thrown away unread, and every byte read reaches ``--raw-out``."""
        ser = self.ser
        now = time.monotonic()
        if now < self._next_poll:
            self._stop.wait(min(self._next_poll - now, 0.05))
            return
        self._next_poll = now + 1.0 / self.rate
        if self._flush_next:
            self._port(ser.reset_input_buffer)
            self._flush_next = False
        self._port(ser.write, b"\x0c\x00")
        deadline = now + 0.2
        got = 0
        while not got and not self._stop.is_set() and time.monotonic() < deadline:
            data = self._port(lambda: ser.read(max(1, ser.in_waiting)))
            if data:
                got = self._got(data, time.monotonic())
        if not self.decoder.pending:
            return
        # bytes of an unfinished answer: wait for the rest while it keeps coming (at most 0.2 s more), then
        # close it (a response that ends only by silence, e.g. pos_get, ends here; a cut one is dropped)
        quiet, limit = time.monotonic() + 0.05, time.monotonic() + 0.2
        while time.monotonic() < min(quiet, limit) and not self._stop.is_set():
            data = self._port(lambda: ser.read(max(1, ser.in_waiting)))
            if data:
                self._got(data, time.monotonic())
                quiet = time.monotonic() + 0.05
        self._emit(self.decoder.finish(), time.monotonic() - self.t0)

    def _init_shell(self) -> None:
        ser = self.ser
        self._port(ser.write, b"\r\r")
        if self._stop.wait(1.1):
            return
        self._port(ser.reset_input_buffer)
        self._port(ser.write, b"lec\r")

    def _init_shell_or_lose(self) -> None:
        try:
            self._init_shell()
        except _PortError as e:
            if not self._reconnect(str(e)):
                self._stop.set()

    def _close_decoder(self) -> None:
        if self.protocol == "dwm1001-shell":
            self.decoder.discard()  # an unfinished line was cut by the stop: never parse a cut number
        else:
            self._emit(self.decoder.finish(), time.monotonic() - self.t0)  # checksummed / structural

    def _fault(self, line: str) -> None:
        self.faults.append(line)
        self.events.put(line)

    def _reconnect(self, reason: str) -> bool:
        """The device is lost: reopen it at the same path for up to `reconnect_s`; False: give up."""
        try:
            if self.ser is not None:
                self.ser.close()
        except Exception:  # noqa: BLE001
            pass
        self.ser = None
        now = time.monotonic()
        self.decoder.discard()
        self.state = "lost"
        self.losses += 1
        if self._lost_since is None or now - self._up_since >= STABLE_S:
            self._lost_since = now  # a device that keeps dropping within 5 s does not reset the clock
        if self.reconnect_s <= 0:
            self._fault(f"{self.port}: device lost ({reason}); the recording ends here (--reconnect 0)")
            self.ended = "device lost"
            return False
        left = self.reconnect_s - (now - self._lost_since)
        self._fault(f"{self.port}: device lost ({reason}); reopening it for up to {max(left, 0):.0f} s")
        tries = 0
        while not self._stop.wait(RETRY_S):
            tries += 1
            try:
                ser = self.opener(self.port, self.baud)
            except Exception as e:  # noqa: BLE001 - not back yet (no such file, busy, ...)
                if time.monotonic() - self._lost_since >= self.reconnect_s:
                    self._fault(
                        f"{self.port}: device did not come back within {self.reconnect_s:g} s "
                        f"({tries} tries, last: {_one_line(e)}); the recording ends here"
                    )
                    self.ended = "device lost"
                    return False
                continue
            self.ser = ser
            self.state = "ok"
            self._flush_next = True
            self.reconnects += 1
            self._up_since = self.last_rx = self.last_frame = time.monotonic()
            self.bytes_since_frame = 0
            self._framed = False
            self._fault(f"{self.port}: device back after {self._up_since - now:.1f} s; recording goes on")
            if self.shell_init:
                try:
                    self._init_shell()
                except _PortError as e:  # one more loss: the loop reopens it
                    try:
                        self.ser.close()
                    except Exception:  # noqa: BLE001
                        pass
                    self.ser, self._why_closed = None, str(e)
            return True
        return False  # stopped while waiting

    # --------------------------------------------------------------------- main-thread checks
    def check(self, now: float) -> list[str]:
        """Fault lines due at host time `now` (no data, garbage), each said once and its end once."""
        out: list[str] = []
        if self.state != "ok":
            return out
        idle = now - self.last_rx
        if idle >= self.stall_s and not self._stalled:
            self._stalled = True
            self.last_gap = 0.0
            out.append(f"{self.port}: no data for {idle:.1f} s ({HINTS[self.protocol]})")
        elif idle < self.stall_s and self._stalled:
            self._stalled = False
            out.append(f"{self.port}: data again after {self.last_gap:.1f} s of silence")
        since, nbytes = now - self.last_frame, self.bytes_since_frame
        k = SHELL_START_FACTOR if self.protocol == "dwm1001-shell" and not self._framed else 1
        if nbytes >= k * GARBAGE_BYTES and since >= k * GARBAGE_S and not self._garbage:
            self._garbage = True
            out.append(
                f"{self.port}: {nbytes} bytes in {since:.1f} s but no valid frame: wrong --baud "
                f"(now {self.baud}) or --protocol (now {self.protocol})?"
            )
        elif self._garbage and nbytes < GARBAGE_BYTES and since < GARBAGE_S:
            self._garbage = False
            out.append(f"{self.port}: valid frames again")
        self.faults.extend(out)
        return out

    def state_text(self, now: float) -> str:
        """Short link state for the status line: ``ok``, ``no data 3 s``, ``garbage``, ``lost 2 s``."""
        if self.state == "lost":
            return f"lost {now - (self._lost_since or now):.0f} s, reopening"
        if self._stalled:
            return f"no data {now - self.last_rx:.0f} s"
        if self._garbage:
            return "garbage (baud?)"
        return "ok"
