"""Pseudo-terminal stand-ins for the serial devices `jaxcal record --port` reads, as a user's device would
be used: the recorder opens the pty's slave path with pyserial, the "device" writes and reads the master.

Used by tests/test_record_pty.py (a fast in-suite version) and benchmarks/record_kill_soak.py (the soak).

* NLink: streams NodeFrame3 frames (a LinkTrack NODE mesh), one write per frame at a nominal rate.
* DWM1001 TLV: answers each ``dwm_loc_get`` request (``0C 00``) with the next tag response.
* DWM1001 shell: waits for ``lec\\r`` (the recorder's ``--init``), echoes it, then streams ``lec`` lines.

`kill_run` kills the recorder with SIGKILL at a chosen frame (optionally after writing only part of it)
and returns what the recorder had read by then (bytes written minus those still unread in the pty, by
FIONREAD on the slave, which the test keeps open), so the journal can be checked against it.
"""

from __future__ import annotations

import fcntl
import os
import random
import select
import signal
import struct
import subprocess
import sys
import termios
import time
import tty
from pathlib import Path

import numpy as np

from jaxcal.io.serial import encode as E
from jaxcal.io.serial.dwm1001 import decode_shell, decode_tlv
from jaxcal.io.serial.nlink import decode as decode_nlink

ROOT = Path(__file__).resolve().parents[1]
RATE_HZ = {"nlink": 100.0, "dwm1001-tlv": 20.0, "dwm1001-shell": 20.0}


def open_pty(link: Path | None = None) -> tuple[int, int, str]:
    """(master, slave, port): a raw pty; with `link`, a symlink at that path (a stable device name, as
    udev's /dev/serial/by-id links) is (re)pointed at the new slave and is the port."""
    master, slave = os.openpty()
    tty.setraw(slave)  # before the recorder opens it: no echo, no line editing
    name = os.ttyname(slave)
    if link is None:
        return master, slave, name
    tmp = link.with_name(link.name + ".new")
    os.symlink(name, tmp)
    os.replace(tmp, link)
    return master, slave, str(link)


def unread(slave: int) -> int:
    """Bytes written to the pty that nobody has read yet (FIONREAD on the slave)."""
    return struct.unpack("i", fcntl.ioctl(slave, termios.FIONREAD, b"\0\0\0\0"))[0]


def settled_unread(slave: int) -> int:
    """`unread` once it stops changing. FIONREAD counts the slave's read queue only: bytes just written
    to the master may still sit in the pty's flip buffer, moved there by a kernel worker a moment later."""
    last = unread(slave)
    while True:
        time.sleep(0.05)
        now = unread(slave)
        if now == last:
            return now
        last = now


def wait_drained(slave: int, timeout: float = 20.0) -> bool:
    """Wait until the recorder has read everything written so far (0 unread, twice 50 ms apart)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        time.sleep(0.05)
        if unread(slave) == 0 and settled_unread(slave) == 0:
            return True
    return False


def write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


# ------------------------------------------------------------------------------------------ payloads


def nlink_frames(n: int, seed: int = 0, first: int = 0) -> list[bytes]:
    """NodeFrame3 frames of four LinkTrack NODE modules ranging each other; each frame is distinct."""
    rng = random.Random(seed)
    pos = [(0, 0), (6000, 0), (2000, 5000), (7000, 6000)]
    out = []
    for i in range(first, first + n):
        me = i % 4
        t = 1000 + 10 * i
        nodes = [
            (
                0,
                j,
                int(np.hypot(pos[me][0] - pos[j][0], pos[me][1] - pos[j][1])) + rng.randint(-30, 30),
                rng.randint(160, 200),
                rng.randint(150, 170),
            )
            for j in range(4)
            if j != me
        ]
        out.append(E.nodeframe3(0, me, t, t, 4900, nodes))
    return out


def tlv_responses(n: int, seed: int = 0) -> list[bytes]:
    """dwm_loc_get answers of a tag ranging three anchors; consecutive answers differ (no duplicates)."""
    rng = random.Random(seed)
    anchors = [(0x1151, (5000, 8000, 2250)), (0x0CA8, (0, 8000, 2250)), (0x111C, (5000, 0, 2250))]
    return [
        E.loc_get_tag((2500, 2000, 1700), 90, [(a, 3000 + 7 * i + rng.randint(0, 5), 100, p, 100) for a, p in anchors])
        for i in range(n)
    ]


def lec_lines(n: int, seed: int = 0) -> list[bytes]:
    """Shell `lec` lines (CRLF) of a tag ranging two anchors."""
    rng = random.Random(seed)
    return [
        E.lec_line(
            [
                ("0CA8", (0, 8, 2.25), 6.5 + rng.randint(0, 50) / 100),
                ("111C", (5, 0, 2.25), 3.2 + rng.randint(0, 50) / 100),
            ],
            (1, 2, 3),
            90,
        )
        for _ in range(n)
    ]


def payloads(protocol: str, n: int, seed: int) -> list[bytes]:
    return {"nlink": nlink_frames, "dwm1001-tlv": tlv_responses, "dwm1001-shell": lec_lines}[protocol](n, seed)


def raws(protocol: str, items: list[bytes]) -> list[bytes]:
    """The validated raw frames the recorder journals for `items` (decoded one by one)."""
    dec = {"nlink": decode_nlink, "dwm1001-tlv": decode_tlv, "dwm1001-shell": decode_shell}[protocol]
    out = []
    for it in items:
        frames, _ = dec(it)
        assert len(frames) == 1, (protocol, it)
        out.append(frames[0].raw)
    return out


def rebaud(data: bytes, rx_bit_per_tx_bit: float) -> bytes:
    """What a UART receiver at the wrong baud rate reads from `data` sent 8N1: the line is sampled with
    bit periods `rx_bit_per_tx_bit` times the sender's (0.5: receiver at twice the sender's baud);
    start bit on a falling edge, data bits at their middles, the byte delivered whatever its stop bit."""
    bits = [1] * 10
    for b in data:
        bits += [0] + [(b >> i) & 1 for i in range(8)] + [1]
    bits += [1] * 20
    L, n, t, out = rx_bit_per_tx_bit, len(bits), 0.0, bytearray()
    step = min(L, 1.0) / 4
    while t + 10 * L < n:
        if bits[int(t)] == 1:
            t += step
            continue
        byte = 0
        for k in range(8):
            byte |= bits[int(t + (1.5 + k) * L)] << k
        out.append(byte)
        t += 9.5 * L  # at the stop bit's middle: hunt the next start bit from there
    return bytes(out)


# ---------------------------------------------------------------------------------------- recorder


def start_recorder(port: str, out: Path, protocol: str, *extra) -> subprocess.Popen:
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT / "src"))
    env.pop("JAXCAL_DEBUG", None)
    args = [
        sys.executable,
        "-m",
        "jaxcal.cli",
        "record",
        "--port",
        port,
        "--protocol",
        protocol,
        "-o",
        str(out),
        *map(str, extra),
    ]
    if protocol == "dwm1001-shell":
        args.append("--init")
    if protocol == "dwm1001-tlv":
        args += ["--rate", str(RATE_HZ[protocol])]
    return subprocess.Popen(args, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for(pred, timeout: float = 60.0) -> bool:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:
            if pred():
                return True
        except (OSError, KeyError):
            pass
        time.sleep(0.02)
    return False


def read_until(master: int, token: bytes, timeout: float = 30.0) -> bool:
    """Read what the recorder writes to the device until `token` was seen."""
    buf, t0 = b"", time.monotonic()
    while time.monotonic() - t0 < timeout:
        r, _, _ = select.select([master], [], [], 0.05)
        if r:
            buf += os.read(master, 256)
            if token in buf:
                return True
    return False


class Device:
    """One simulated module on a pty master: `send(item)` streams (NLink, shell) or answers the next
    request (TLV). `ends[i]`: stream offset just after item i (offsets count from the first item)."""

    def __init__(self, protocol: str, master: int, slave: int | None = None) -> None:
        self.protocol, self.master, self.slave = protocol, master, slave
        self.written = 0
        # with `slave`: the most items a read of the recorder's can have completed, and the most bytes it
        # can have held (what was unread just before a write, plus the write): a recorder the machine
        # starves reads several items at once, and a kill in that read loses them all
        self.max_read_items, self.max_read_bytes = 1, 0
        self.stream = bytearray()  # every byte written after `begin` (what the recorder can read)
        self.ends: list[int] = []
        self.period = 1.0 / RATE_HZ[protocol]
        self._next = time.monotonic()

    def begin(self) -> bool:
        """Shell: wait for `lec` and echo it (the echo line is ignored by the reader, not counted)."""
        if self.protocol != "dwm1001-shell":
            return True
        if not read_until(self.master, b"lec\r"):
            return False
        echo = b"dwm> lec\r\n"
        write_all(self.master, echo)
        self.written = len(echo)
        self.stream += echo
        return True

    def _wait_request(self, timeout: float = 30.0) -> bool:
        need, buf, t0 = b"\x0c\x00", b"", time.monotonic()
        while time.monotonic() - t0 < timeout:
            r, _, _ = select.select([self.master], [], [], 0.05)
            if r:
                buf += os.read(self.master, 64)
                if need in buf:
                    return True
        return False

    def send(self, item: bytes, upto: int | None = None) -> bool:
        """Deliver `item` (only its first `upto` bytes when given); False if the recorder stopped asking."""
        delay = 1.0  # TLV answers a request: the recorder has read the answer before
        if self.protocol == "dwm1001-tlv":
            if not self._wait_request():
                return False
        else:
            delay = self._next - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            self._next = max(self._next + self.period, time.monotonic() - self.period)
        part = item if upto is None else item[:upto]
        if self.slave is not None:
            # behind schedule, the last write may still sit in the pty's flip buffer, unseen by FIONREAD
            pending = unread(self.slave) if delay > 0 else settled_unread(self.slave)
            whole = len(self.ends) - self.complete(self.written - pending) + (upto is None)
            self.max_read_items = max(self.max_read_items, whole)
            self.max_read_bytes = max(self.max_read_bytes, pending + len(part))
        write_all(self.master, part)
        self.written += len(part)
        self.stream += part
        if upto is None:
            self.ends.append(self.written)
        return True

    def complete(self, nbytes: int) -> int:
        """Items completely inside the first `nbytes` stream bytes."""
        return int(np.searchsorted(np.asarray(self.ends), nbytes, side="right"))


def kill_run(tmp: Path, protocol: str, seed: int, n_items: int) -> dict:
    """Record from a pty, SIGKILL the recorder at a random item (a random part of it written), and return
    the figures: items sent, items the recorder had read completely, journal frames (checked against
    the items: a prefix), whether the snapshot existed at the kill."""
    from jaxcal.io.recorder import replay

    rng = random.Random(seed)
    kill_at = rng.randrange(1, n_items)
    item = payloads(protocol, n_items, seed)
    split = rng.randrange(0, len(item[kill_at]))  # 0: killed between two items
    master, slave, port = open_pty()
    out = tmp / f"kill-{protocol}-{seed}.h5"
    raw_out = tmp / f"kill-{protocol}-{seed}.bin"
    proc = start_recorder(port, out, protocol, "--quiet", "--raw-out", raw_out)
    dev = Device(protocol, master, slave)
    try:
        assert wait_for(lambda: Path(str(out) + ".journal").exists()), proc.stderr and proc.communicate()[1]
        assert dev.begin(), "the recorder never sent lec"
        for i in range(kill_at):
            assert dev.send(item[i]), f"no request for item {i}"
        if split:
            dev.send(item[kill_at], upto=split)
        time.sleep(rng.random() * dev.period)  # anywhere in the reader's cycle
        snapshot = out.exists()
        proc.send_signal(signal.SIGKILL)
        _, err = proc.communicate(timeout=30)
        read = dev.written - settled_unread(slave)  # the recorder is dead: what is left was never read
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)
        os.close(slave)
    complete = dev.complete(read)
    raw = raw_out.read_bytes()  # --raw-out: every byte read, written before it is decoded
    assert raw == bytes(dev.stream[: len(raw)]), "the raw capture is not what was sent"
    rec = replay(str(out) + ".journal", None, {})
    expected = raws(protocol, item[:kill_at])
    got = rec.raw
    snap = None  # frames in the snapshot left by the kill: a complete contract file, a prefix of the journal
    if out.exists():
        from jaxcal.io import hdf5

        hdf5.read(out)
        snap = replay(out, None, {}).raw
        assert snap == got[: len(snap)], "the snapshot is not a prefix of the journal"
    return {
        "protocol": protocol,
        "seed": seed,
        "sent": kill_at,
        "partial": split > 0,
        "read_complete": complete,
        "recovered": len(got),
        "prefix": got == expected[: len(got)],
        "snapshot_at_kill": snapshot,
        "snapshot_frames": None if snap is None else len(snap),
        "raw_bytes": len(raw),
        "read_bytes": read,
        "max_item": max(map(len, item)),
        "max_read_items": dev.max_read_items,
        "max_read_bytes": dev.max_read_bytes,
        "stderr": err,
        "out": out,
    }


def kill_ok(r: dict) -> bool:
    """The kill lost nothing it should not have: the journal is a prefix of what was sent and holds every
    frame read completely but those of the read in flight (one while the recorder keeps up; the largest
    read the device measured when the machine starved it), and --raw-out every byte read but that read."""
    lost = r["read_complete"] - r["recovered"]
    return bool(
        r["prefix"]
        and 0 <= lost <= r["max_read_items"]
        and r["read_complete"] <= r["sent"]
        and r["read_bytes"] - r["max_read_bytes"] <= r["raw_bytes"] <= r["read_bytes"]
    )
