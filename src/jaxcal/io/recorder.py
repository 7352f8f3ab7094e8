"""Crash-safe recording of UWB ranges from a serial device into a jaxcal contract file.

Design (crash safety). Two files are kept while recording to ``OUT.h5``:

* an append-only **journal** ``OUT.h5.journal``: a header, then one record per validated raw frame
  (``u32 length, f64 time, payload, u32 crc32``), written and ``fsync``'d at every flush (at least once
  per second). A kill can only tear the last record, which the reader detects by its length or CRC and
  drops. The journal alone can rebuild the recording: ``jaxcal record --replay OUT.h5.journal -o OUT.h5``;
* an HDF5 **snapshot** ``OUT.h5``, rewritten atomically (temporary file, fsync, ``os.replace``) at each
  flush once the ranges make a valid dataset, so that ``OUT.h5`` is always a complete, readable contract
  file holding everything up to the last snapshot. When a snapshot takes long (big recordings), it is
  rewritten less often (at most 10 % of the time is spent on it); the journal is still flushed every
  second. On a clean stop (``--duration``, Ctrl-C, SIGTERM) the final snapshot is written and the
  journal removed.

The snapshot also holds the raw validated frames in the optional group ``raw`` (``raw/frames``: all
frames' bytes concatenated, uint8; ``raw/offsets``: (F + 1,) int64 frame boundaries; ``raw/time``: (F,)
float64 frame times [s]; attributes ``protocol``, ``time_source``, ``start_wall_time``, ``self_id``,
``epoch_s``), so a recording can be re-decoded by a fixed decoder: ``jaxcal record --replay OUT.h5``.

Mapping of frames to the contract (see `build_dataset`):

* **time**: live, a frame's time is the host's monotonic clock at the read that completed it, in
  seconds since the recording started (device clocks of different modules are not synchronised).
  Replaying a raw byte capture, which has no host times, NLink frames use the module's ``local_time``
  (ms, unwrapped at 2^32, never going back) relative to the first frame; DWM1001 output carries no
  device time, so frame ``i`` gets ``i / rate``.
* **format**: ``trajectory`` when every range has exactly one tag end (LinkTrack tag frames, NodeFrame4,
  TagFrame0, AnchorFrame0 tag slots, DWM1001 tag/anchor output), otherwise ``mesh`` (e.g. LinkTrack
  distributed-ranging NODE frames, anchor-to-anchor ranges); ``--format`` forces one.
* **mesh**: nodes are all ids seen, in order of first appearance. Asynchronous frames are grouped into
  epochs by binning their times into consecutive windows of ``epoch_s`` seconds from the first frame
  (empty windows are left out); ``range[k, i, j]`` is the mean of the i->j ranges in window k (NaN
  when none), likewise the powers; the epoch time is the mean time of its ranges.
* **trajectory**: anchors are the non-tag ends, tags the tag ends; one ``ranges`` row per measurement.
  No pose source is recorded, so the file holds a **placeholder pose stream**: two poses, static at the
  origin, spanning the ranges' times; the root ``description`` says so, and ``raw`` carries the
  attribute ``placeholder_poses = 1``. Replace the poses before a trajectory calibration.
* Negative ranges (UWB bias at short distance) cannot be stored (the contract wants ranges >= 0) and are
  counted in ``negative_ranges``; the raw frames keep them. Consecutive identical DWM1001 TLV location
  responses (the module answers the last result again between updates) are counted as ``duplicates``
  and their ranges used once.
"""

from __future__ import annotations

import json
import math
import os
import queue
import signal
import struct
import sys
import threading
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from jaxcal.errors import JaxcalError
from jaxcal.io.serial import PROTOCOLS, make_decoder
from jaxcal.io.serial.frames import Frame

__all__ = [
    "JOURNAL_MAGIC",
    "JournalWriter",
    "read_journal",
    "Recording",
    "replay",
    "record_serial",
    "DEFAULT_BAUD",
]

JOURNAL_MAGIC = b"JXCJRNL1"
HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
DEFAULT_BAUD = {"nlink": 921600, "dwm1001-tlv": 115200, "dwm1001-shell": 115200}
_REC = struct.Struct("<Id")


# -------------------------------------------------------------------------------------------- journal


class JournalWriter:
    """Append-only journal of raw frames; `flush()` writes the buffered records and fsyncs."""

    def __init__(self, path: str | os.PathLike, header: dict) -> None:
        self.path = Path(path)
        self._f = open(self.path, "xb")  # never overwrite: an existing journal is an unrecovered recording
        h = json.dumps(header).encode()
        self._pending = [JOURNAL_MAGIC + struct.pack("<I", len(h)) + h]
        self.flush()

    def append(self, raw: bytes, t: float) -> None:
        """Queue one frame record (written at the next flush)."""
        self._pending.append(_REC.pack(len(raw), t) + raw + struct.pack("<I", zlib.crc32(raw)))

    def flush(self) -> None:
        """Write queued records and fsync the file."""
        if self._pending:
            self._f.write(b"".join(self._pending))
            self._pending.clear()
        self._f.flush()
        os.fsync(self._f.fileno())

    def close(self) -> None:
        """Flush and close."""
        if not self._f.closed:
            self.flush()
            self._f.close()


def read_journal(path: str | os.PathLike) -> tuple[dict, list[tuple[float, bytes]], int]:
    """Read a journal. Returns (header, [(time_s, raw frame)], torn_bytes): a torn or corrupt tail is
    dropped and its size returned (a kill mid-write leaves at most one partial record)."""
    data = Path(path).read_bytes()
    if not data.startswith(JOURNAL_MAGIC) or len(data) < 12:
        raise JaxcalError(f"{path}: not a jaxcal record journal")
    (hl,) = struct.unpack_from("<I", data, 8)
    try:
        header = json.loads(data[12 : 12 + hl])
    except ValueError:
        raise JaxcalError(f"{path}: journal header is corrupt") from None
    o = 12 + hl
    out = []
    while o + _REC.size <= len(data):
        n, t = _REC.unpack_from(data, o)
        e = o + _REC.size + n
        if e + 4 > len(data):
            break
        raw = data[o + _REC.size : e]
        if zlib.crc32(raw) != struct.unpack_from("<I", data, e)[0]:
            break
        out.append((t, raw))
        o = e + 4
    return header, out, len(data) - o


# ------------------------------------------------------------------------------------------ recording


class Recording:
    """Frames and ranges accumulated so far, and their mapping to a contract dataset.

    Args:
        protocol: one of `jaxcal.io.serial.PROTOCOLS`.
        epoch_s: mesh epoch window [s].
        fmt: ``"auto"``, ``"mesh"`` or ``"trajectory"``.
        name: dataset name written to the file.
        self_id: DWM1001 id of the module on the port (see `make_decoder`).
    """

    def __init__(self, protocol: str, epoch_s: float = 0.1, fmt: str = "auto", name: str = "recording",
                 self_id: str | None = None) -> None:
        if protocol not in PROTOCOLS:
            raise JaxcalError(f"unknown protocol {protocol!r} (known: {', '.join(PROTOCOLS)})")
        if not epoch_s > 0:
            raise JaxcalError(f"--epoch must be positive, got {epoch_s}")
        if fmt not in ("auto", "mesh", "trajectory"):
            raise JaxcalError(f"--format must be auto, mesh or trajectory, got {fmt!r}")
        self.protocol, self.epoch_s, self.fmt, self.name, self.self_id = protocol, epoch_s, fmt, name, self_id
        self.decoder = make_decoder(protocol, self_id)
        self.raw: list[bytes] = []
        self.raw_time: list[float] = []
        self.ids: dict[str, int] = {}
        self.roles: dict[str, set[str]] = {}
        self._rows: list[tuple] = []  # (t, src, dst, range, fp, rx, src_is_tag, dst_is_tag), pending
        self._cols: dict[str, np.ndarray] | None = None
        self.n_ranges = 0
        self.negative_ranges = 0
        self.duplicates = 0
        self._last_loc: bytes | None = None
        self.time_source = "host"
        self.start_wall_time = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        self.journal: JournalWriter | None = None
        self.frame_ids: tuple[str, str, str] | None = None  # written as the mesh's `default` configuration

    # ---- ingestion
    def add(self, frames: list[Frame], t: float) -> int:
        """Record decoded frames received at time `t` [s]; returns the number of ranges added."""
        added = 0
        for f in frames:
            self.raw.append(f.raw)
            self.raw_time.append(t)
            if self.journal is not None:
                self.journal.append(f.raw, t)
            if self.protocol == "dwm1001-tlv" and f.type.startswith("loc_get"):
                if f.raw == self._last_loc:
                    self.duplicates += 1
                    continue
                self._last_loc = f.raw
            for r in f.ranges:
                if not (math.isfinite(r.range_m) and r.range_m >= 0):
                    self.negative_ranges += 1
                    continue
                si, di = self._index(r.src, r.src_role), self._index(r.dst, r.dst_role)
                self._rows.append((t, si, di, r.range_m, r.fp_rssi, r.rx_rssi, r.src_role == "tag", r.dst_role == "tag"))
                added += 1
        self.n_ranges += added
        return added

    def _index(self, ident: str, role: str) -> int:
        i = self.ids.get(ident)
        if i is None:
            i = self.ids[ident] = len(self.ids)
            self.roles[ident] = set()
        self.roles[ident].add(role)
        return i

    def columns(self) -> dict[str, np.ndarray]:
        """All ranges so far as columns (pending rows are converted once, then concatenated)."""
        names = ("time", "src", "dst", "range", "fp_rssi", "rx_rssi", "src_tag", "dst_tag")
        dtypes = (np.float64, np.int64, np.int64, np.float64, np.float64, np.float64, bool, bool)
        if self._cols is None:
            self._cols = {n: np.zeros(0, d) for n, d in zip(names, dtypes)}
        if self._rows:
            cols = list(zip(*self._rows))
            self._cols = {n: np.concatenate([self._cols[n], np.asarray(c, d)]) for n, c, d in zip(names, cols, dtypes)}
            self._rows = []
        return self._cols

    # ---- mapping to the contract
    def kind(self) -> str | None:
        """``"mesh"`` or ``"trajectory"`` for the ranges so far (None when there are none)."""
        if self.fmt != "auto":
            return self.fmt
        c = self.columns()
        if c["time"].size == 0:
            return None
        return "trajectory" if bool(np.all(c["src_tag"] ^ c["dst_tag"])) else "mesh"

    def build_dataset(self):
        """The contract dataset of everything recorded so far, or None while it cannot be valid yet
        (no ranges, fewer than 3 mesh nodes)."""
        kind = self.kind()
        if kind is None:
            return None
        return self._mesh() if kind == "mesh" else self._trajectory()

    def _source(self) -> str:
        return f"jaxcal record, protocol {self.protocol}, started {self.start_wall_time}"

    def _mesh(self):
        from jaxcal.data import MeshDataset

        c = self.columns()
        n = len(self.ids)
        if n < 3 or c["time"].size == 0:
            return None
        t = c["time"]
        # 1e-9: a time on a window boundary (e.g. 0.6 s / 0.2 s = 2.9999999999999996) opens the next window
        b = np.floor((t - t.min()) / self.epoch_s + 1e-9).astype(np.int64)
        bins, k = np.unique(b, return_inverse=True)
        K = bins.size
        flat = (k * n + c["src"]) * n + c["dst"]
        size = K * n * n

        def mean(v):
            ok = np.isfinite(v)
            s = np.bincount(flat[ok], weights=v[ok], minlength=size)
            m = np.bincount(flat[ok], minlength=size)
            with np.errstate(invalid="ignore", divide="ignore"):
                return np.where(m > 0, s / np.maximum(m, 1), np.nan).reshape(K, n, n), bool(ok.any())

        rng, _ = mean(c["range"])
        fp, has_fp = mean(c["fp_rssi"])
        rx, has_rx = mean(c["rx_rssi"])
        et = np.bincount(k, weights=t, minlength=K) / np.bincount(k, minlength=K)
        idx = np.arange(n)
        rng[:, idx, idx] = np.nan  # a node ranging itself is not a measurement
        configs = ()
        if self.frame_ids is not None and all(i in self.ids for i in self.frame_ids):
            configs = (("default", tuple(self.ids[i] for i in self.frame_ids)),)
        return MeshDataset(
            name=self.name, node_ids=list(self.ids), time=et, range=rng,
            fp_rssi=fp if has_fp else None, rx_rssi=rx if has_rx else None, configs=configs,
            description=(
                f"Recorded by jaxcal record ({self.protocol}). Epochs: {self.epoch_s:g} s windows of "
                f"{self.time_source} time; range = mean of the window's measurements. Raw frames in /raw."
            ),
            source=self._source(),
        )

    def _trajectory(self):
        from jaxcal.data import TrajectoryDataset

        c = self.columns()
        if c["time"].size == 0:
            return None
        # the tag end of each range; with no tag end (forced trajectory) the reporting node is the tag
        src_is_tag = c["src_tag"] | ~c["dst_tag"]
        tag_g = np.where(src_is_tag, c["src"], c["dst"])
        anc_g = np.where(src_is_tag, c["dst"], c["src"])
        names = list(self.ids)
        tags_u, tag_i = np.unique(tag_g, return_inverse=True)
        anc_u, anc_i = np.unique(anc_g, return_inverse=True)
        order = np.argsort(c["time"], kind="stable")
        t = c["time"][order]
        t0, t1 = float(t[0]), float(t[-1])
        t1 = max(t1, t0 + 1e-3)
        fp, rx = c["fp_rssi"][order], c["rx_rssi"][order]
        return TrajectoryDataset(
            name=self.name,
            anchor_ids=[names[i] for i in anc_u],
            tag_ids=[names[i] for i in tags_u],
            lever_arm=np.zeros((tags_u.size, 3)),
            pose_time=np.array([t0, t1]),
            pose_position=np.zeros((2, 3)),
            range_time=t,
            range_anchor=anc_i[order],
            range_tag=tag_i[order],
            range=c["range"][order],
            fp_rssi=fp if np.isfinite(fp).any() else None,
            rx_rssi=rx if np.isfinite(rx).any() else None,
            description=(
                f"Recorded by jaxcal record ({self.protocol}). PLACEHOLDER POSES: no pose source was "
                f"recorded; the two poses are static at the origin and only span the range times "
                f"({self.time_source} time). Raw frames in /raw."
            ),
            source=self._source(),
        )

    # ---- output
    def write(self, path: str | os.PathLike) -> bool:
        """Write the contract file plus the `raw` group atomically. Returns False when no valid dataset
        can be built yet (nothing is written)."""
        import h5py

        from jaxcal.io import hdf5

        ds = self.build_dataset()
        if ds is None:
            return False
        path = Path(path)
        tmp = path.with_name(f".{path.name}.snapshot.tmp")
        try:
            hdf5.write(tmp, ds)
            with h5py.File(tmp, "a") as f:
                g = f.create_group("raw")
                lens = np.fromiter((len(r) for r in self.raw), np.int64, len(self.raw))
                off = np.zeros(lens.size + 1, np.int64)
                np.cumsum(lens, out=off[1:])
                big = {"compression": "gzip", "compression_opts": 1} if off[-1] > 4096 else {}
                g.create_dataset("frames", data=np.frombuffer(b"".join(self.raw), np.uint8), **big)
                g.create_dataset("offsets", data=off)
                g.create_dataset("time", data=np.asarray(self.raw_time, np.float64))
                g.attrs.update(
                    protocol=self.protocol, time_source=self.time_source, start_wall_time=self.start_wall_time,
                    self_id=self.self_id or "", epoch_s=self.epoch_s,
                    placeholder_poses=int(not hasattr(ds, "node_ids")),
                    decoder_stats=json.dumps(self.decoder.stats.as_dict()),
                )
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()
        return True

    def summary(self) -> dict:
        """Counters for `--json` and the status line."""
        s = self.decoder.stats.as_dict()
        s.update(
            ranges=self.n_ranges, negative_ranges=self.negative_ranges, duplicates=self.duplicates,
            nodes=len(self.ids), format=self.kind(), protocol=self.protocol,
        )
        return s


# ---------------------------------------------------------------------------------------------- replay


class _DeviceClock:
    """Frame times from a raw capture: NLink local_time (ms) unwrapped and kept monotone; else i / rate."""

    def __init__(self, protocol: str, rate: float) -> None:
        self.protocol, self.rate = protocol, rate
        self.first: int | None = None
        self.last_raw = 0
        self.offset = 0
        self.t = 0.0
        self.count = 0

    def __call__(self, f: Frame) -> float:
        self.count += 1
        if self.protocol != "nlink":
            return (self.count - 1) / self.rate
        ms = f.device_time_ms
        if ms is None:
            return self.t
        if self.first is None:
            self.first = self.last_raw = ms
        if ms < self.last_raw and self.last_raw - ms > (1 << 31):
            self.offset += 1 << 32  # 32-bit counter wrapped (about 49.7 days)
        self.last_raw = ms
        self.t = max(self.t, (ms + self.offset - self.first) / 1000.0)
        return self.t


def _reframe(protocol: str, raw: bytes) -> bytes:
    return raw + b"\n" if protocol == "dwm1001-shell" else raw


def replay(path: str | os.PathLike, protocol: str | None, rec_kwargs: dict, rate: float = 10.0,
           on_flush: Callable[[Recording], None] | None = None, flush_s: float = 1.0) -> Recording:
    """Decode a raw byte capture, a recorder journal or a recorded HDF5 file (its `raw` group).

    Args:
        path: the input; its kind is detected from its first bytes.
        protocol: required for a raw capture; for a journal or HDF5 file it must match the stored one
            (or be None).
        rec_kwargs: keyword arguments of `Recording` (epoch_s, fmt, name, self_id).
        rate: frames per second assumed for DWM1001 captures (no device time).
        on_flush: called with the recording whenever `flush_s` seconds of frame time have passed since
            the last call, as the live recorder calls it at each flush (live calibration).

    Returns:
        The `Recording`, ready to `write`.
    """
    p = Path(path)
    if not p.is_file():
        raise JaxcalError(f"{p}: no such file")
    with open(p, "rb") as fh:
        head = fh.read(8)
    stored = None
    if head == HDF5_MAGIC:
        stored, records = _read_h5_raw(p)
    elif head == JOURNAL_MAGIC:
        header, records, _torn = read_journal(p)
        stored = header
    if stored is not None:
        sp = stored.get("protocol")
        if protocol is not None and protocol != sp:
            raise JaxcalError(f"{p}: recorded with protocol {sp}, not {protocol}")
        kw = {k: v for k, v in rec_kwargs.items() if k != "frame_ids"}
        if not kw.get("self_id") and stored.get("self_id"):
            kw["self_id"] = stored["self_id"]
        rec = Recording(sp, **kw)
        rec.frame_ids = rec_kwargs.get("frame_ids")
        flush = _Flusher(rec, on_flush, flush_s)
        rec.time_source = stored.get("time_source", "host")
        rec.start_wall_time = stored.get("start_wall_time", rec.start_wall_time)
        dec = rec.decoder
        for t, raw in records:
            rec.add(dec.feed(_reframe(sp, raw)) + dec.finish(), t)
            flush(t)
        return rec
    if protocol is None:
        raise JaxcalError("--protocol is required to replay a raw byte capture")
    rec = Recording(protocol, **{k: v for k, v in rec_kwargs.items() if k != "frame_ids"})
    rec.frame_ids = rec_kwargs.get("frame_ids")
    flush = _Flusher(rec, on_flush, flush_s)
    rec.time_source = "device" if protocol == "nlink" else f"frame index / {rate:g} Hz"
    clock = _DeviceClock(protocol, rate)
    dec = rec.decoder
    with open(p, "rb") as fh:
        while chunk := fh.read(1 << 16):
            for f in dec.feed(chunk):
                t = clock(f)
                rec.add([f], t)
                flush(t)
    for f in dec.finish():
        rec.add([f], clock(f))
    return rec


class _Flusher:
    """Calls `on_flush(rec)` each time frame time passes the next multiple of `flush_s` (replay)."""

    def __init__(self, rec: Recording, on_flush, flush_s: float) -> None:
        self.rec, self.on_flush, self.flush_s, self.next = rec, on_flush, flush_s, None

    def __call__(self, t: float) -> None:
        if self.on_flush is None:
            return
        if self.next is None:
            self.next = t + self.flush_s
        elif t >= self.next:
            self.on_flush(self.rec)
            self.next = t + self.flush_s


def _read_h5_raw(p: Path) -> tuple[dict, list[tuple[float, bytes]]]:
    import h5py

    try:
        with h5py.File(p, "r") as f:
            if "raw" not in f or not {"frames", "offsets", "time"} <= set(f["raw"]):
                raise JaxcalError(f"{p}: has no raw frames (group /raw) to re-decode")
            g = f["raw"]
            data = g["frames"][()].tobytes()
            off = g["offsets"][()]
            t = g["time"][()]
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in g.attrs.items()}
    except OSError as e:
        raise JaxcalError(f"{p}: not a readable HDF5 file ({str(e).splitlines()[0]})") from None
    if off.size != t.size + 1 or off[-1] != len(data):
        raise JaxcalError(f"{p}: /raw is inconsistent (offsets do not match frames)")
    return {k: str(v) for k, v in attrs.items()}, [(float(t[i]), data[off[i] : off[i + 1]]) for i in range(t.size)]


# -------------------------------------------------------------------------------------------- live


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
) -> str:
    """Read `port` until `duration` seconds pass, Ctrl-C or SIGTERM; journal + snapshot as described in
    the module docstring. Returns why it stopped (``"duration"``, ``"interrupt"``, ``"sigterm"``).

    Args:
        rec: the `Recording` to fill (its protocol selects the reader).
        port: a device path or any pyserial URL (``loop://``, ``socket://``, a pty path).
        out: the HDF5 file; the journal is ``out + ".journal"``.
        baud: baud rate (default per protocol: NLink 921600, DWM1001 115200).
        duration: seconds to record (None: until stopped).
        raw_out: also write every byte read to this file (a raw capture for `replay`).
        flush_s: journal flush period [s] (at most 1 s is allowed by the CLI).
        rate: DWM1001 TLV polling rate [Hz].
        shell_init: DWM1001 shell: send ``\\r\\r``, wait 1.1 s, send ``lec\\r`` (lec toggles the stream).
        status: callback(summary, elapsed_s, final) for the status line.
        on_flush: called with the recording after each journal flush (live calibration); its
            exceptions are the caller's to contain.
    """
    import serial  # pyserial

    out = Path(out)
    if not out.parent.exists():
        raise JaxcalError(f"{out}: folder {out.parent} does not exist")
    jpath = Path(str(out) + ".journal")
    if jpath.exists():
        raise JaxcalError(
            f"{jpath} exists (an interrupted recording?): rebuild it with `jaxcal record --replay {jpath} -o {out}`"
            " or delete it"
        )
    baud = baud or DEFAULT_BAUD[rec.protocol]
    import h5py  # noqa: F401 - heavy imports before the port opens, not during the first snapshot

    import jaxcal.io.hdf5  # noqa: F401

    try:
        ser = serial.serial_for_url(port, baudrate=baud, timeout=0.05)
    except (serial.SerialException, ValueError, OSError) as e:
        raise JaxcalError(f"{port}: cannot open serial port ({' '.join(str(e).split())})") from None
    rawf = open(raw_out, "wb") if raw_out else None
    rec.journal = JournalWriter(
        jpath, {"protocol": rec.protocol, "self_id": rec.self_id or "", "time_source": "host",
                "start_wall_time": rec.start_wall_time, "port": port, "baud": baud},
    )
    stop = {"why": None}

    def on_term(signum, frame):
        stop["why"] = "sigterm"

    old = signal.signal(signal.SIGTERM, on_term)
    t0 = time.monotonic()
    last_flush = last_snap = last_status = t0
    snap_cost = 0.0
    dec = rec.decoder
    reader = None
    try:
        if rec.protocol == "dwm1001-shell" and shell_init:
            ser.write(b"\r\r")
            time.sleep(1.1)
            ser.reset_input_buffer()
            ser.write(b"lec\r")
        next_poll = t0
        while stop["why"] is None:
            now = time.monotonic()
            if duration is not None and now - t0 >= duration:
                stop["why"] = "duration"
                break
            if rec.protocol == "dwm1001-tlv":
                if now < next_poll:
                    time.sleep(min(next_poll - now, 0.05))
                    continue
                next_poll = now + 1.0 / rate
                ser.reset_input_buffer()
                ser.write(b"\x0c\x00")  # dwm_loc_get, one write (the module delimits requests by idle time)
                deadline = time.monotonic() + 0.2
                frames: list[Frame] = []
                while time.monotonic() < deadline and not frames:
                    data = ser.read(max(1, ser.in_waiting))
                    if data:
                        if rawf:
                            rawf.write(data)
                        frames = dec.feed(data)
                frames += dec.finish()
                rec.add(frames, time.monotonic() - t0)
            else:
                if reader is None:
                    reader = _Reader(ser)
                try:
                    data, t_read = reader.queue.get(timeout=0.05)
                except queue.Empty:
                    data = b""
                if reader.error is not None:
                    raise JaxcalError(f"{port}: read failed ({reader.error})")
                if data:
                    if rawf:
                        rawf.write(data)
                    rec.add(dec.feed(data), t_read - t0)
            now = time.monotonic()
            if now - last_flush >= flush_s:
                rec.journal.flush()
                if rawf:
                    rawf.flush()
                last_flush = now
                # the snapshot is rewritten whole: keep it under ~10 % of the time for big recordings
                if now - last_snap >= max(flush_s, min(10 * snap_cost, 60.0)):
                    s0 = time.monotonic()
                    if rec.write(out):
                        snap_cost = time.monotonic() - s0
                    last_snap = now
                if on_flush is not None:
                    on_flush(rec)
            if status is not None and now - last_status >= 0.5:
                status(rec.summary(), now - t0, False)
                last_status = now
    except KeyboardInterrupt:
        stop["why"] = "interrupt"
    finally:
        signal.signal(signal.SIGTERM, old)
        if reader is not None:
            reader.stop()
            while not reader.queue.empty():
                data, t_read = reader.queue.get()
                if rawf:
                    rawf.write(data)
                rec.add(dec.feed(data), t_read - t0)
        try:
            ser.close()
        except Exception:  # noqa: BLE001 - closing a vanished port must not hide the recording
            pass
        rec.add(dec.finish(), time.monotonic() - t0)
        rec.journal.close()
        if rawf:
            rawf.close()
    if status is not None:
        status(rec.summary(), time.monotonic() - t0, True)
    return stop["why"] or "duration"


class _Reader:
    """Reads the port on a thread, so that bytes keep flowing while a snapshot is written (a serial
    driver's buffer holds well under a second at 921600 baud). Items: (bytes, host monotonic time)."""

    def __init__(self, ser) -> None:
        self.ser = ser
        self.queue: queue.Queue = queue.Queue()
        self.error: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="jaxcal-serial-reader", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                data = self.ser.read(max(1, self.ser.in_waiting))
                if data:
                    self.queue.put((data, time.monotonic()))
        except Exception as e:  # noqa: BLE001 - reported by the main loop as one line
            self.error = " ".join(str(e).split()) or type(e).__name__
            self.queue.put((b"", time.monotonic()))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)


def finish_journal(rec: Recording, keep: bool) -> None:
    """After the final snapshot was written: remove the journal unless `keep`."""
    if rec.journal is not None and not keep:
        try:
            rec.journal.path.unlink()
        except FileNotFoundError:
            pass


def status_printer(stream=sys.stderr) -> Callable[[dict, float, bool], None]:
    """A status-line callback: rewrites one line on a terminal, prints a line every 5 s otherwise."""
    tty = stream.isatty()
    state = {"t": 0.0, "frames": 0, "ranges": 0, "printed": -1e9}

    def show(s: dict, elapsed: float, final: bool) -> None:
        dt = max(elapsed - state["t"], 1e-9)
        fps = (s["frames"] - state["frames"]) / dt
        rps = (s["ranges"] - state["ranges"]) / dt
        state.update(t=elapsed, frames=s["frames"], ranges=s["ranges"])
        line = (f"{elapsed:7.1f} s  frames {s['frames']} ({fps:.1f}/s)  ranges {s['ranges']} ({rps:.1f}/s)  "
                f"checksum failures {s['checksum_failures']}  skipped {s['bytes_skipped']} B  nodes {s['nodes']}")
        if tty:
            stream.write("\r" + line + ("\n" if final else "\x1b[K"))
        elif final or elapsed - state["printed"] >= 5.0:
            stream.write(line + "\n")
            state["printed"] = elapsed
        stream.flush()

    return show
