"""Crash-safe recording of UWB ranges from a serial device into a jaxcal contract file.

Design (crash safety). Two files are kept while recording to ``OUT.h5`` (the live loop is
`jaxcal.io.capture.record_serial`, its reader thread `jaxcal.io.link`):

* an append-only **journal** ``OUT.h5.journal`` (`jaxcal.io.journal`): a header, then one record per
  validated raw frame (``u32 length, f64 time, payload, u32 crc32``), handed to the kernel (`os.write`)
  by the reader thread as soon as the frame is decoded, before the next read, and ``fsync``'d on the
  flush period (1 s). A SIGKILL loses at most the frame being decoded; a kill can only tear the last
  record, which the reader detects by its length or CRC and drops. The journal alone rebuilds the
  recording: ``jaxcal record --replay OUT.h5.journal -o OUT.h5`` (the recovery command);
* an HDF5 **snapshot** ``OUT.h5``, rewritten atomically (temporary file, fsync, ``os.replace``, fsync of
  the folder) at each flush once the ranges make a valid dataset, so that ``OUT.h5`` is always a
  complete, readable contract file holding everything up to the last snapshot (a subset of the
  journal). When a snapshot takes long (big recordings), it is rewritten less often (at most 10 % of
  the time is spent on it). On a clean stop (``--duration``, Ctrl-C, SIGTERM, a device that did not come
  back) the final snapshot is written and the journal removed.

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
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from jaxcal.errors import JaxcalError
from jaxcal.io.journal import JOURNAL_MAGIC, JournalWriter, read_journal, sync_dir
from jaxcal.io.serial import PROTOCOLS, make_decoder
from jaxcal.io.serial.frames import Frame

__all__ = [
    "JOURNAL_MAGIC",
    "JournalWriter",
    "read_journal",
    "Recording",
    "replay",
    "DEFAULT_BAUD",
]

HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
DEFAULT_BAUD = {"nlink": 921600, "dwm1001-tlv": 115200, "dwm1001-shell": 115200}


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

    def __init__(
        self,
        protocol: str,
        epoch_s: float = 0.1,
        fmt: str = "auto",
        name: str = "recording",
        self_id: str | None = None,
    ) -> None:
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
        self.journal: JournalWriter | None = None  # live: written by the reader thread (`jaxcal.io.link`)
        self.frame_ids: tuple[str, str, str] | None = None  # written as the mesh's `default` configuration
        self.link: dict | None = None  # live: link counters and fault lines (`jaxcal.io.capture`)

    # ---- ingestion
    def add(self, frames: list[Frame], t: float) -> int:
        """Record decoded frames received at time `t` [s]; returns the number of ranges added."""
        added = 0
        for f in frames:
            self.raw.append(f.raw)
            self.raw_time.append(t)
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
                self._rows.append(
                    (t, si, di, r.range_m, r.fp_rssi, r.rx_rssi, r.src_role == "tag", r.dst_role == "tag")
                )
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
            self._cols = {n: np.zeros(0, d) for n, d in zip(names, dtypes, strict=False)}
        if self._rows:
            cols = list(zip(*self._rows, strict=False))
            self._cols = {
                n: np.concatenate([self._cols[n], np.asarray(c, d)])
                for n, c, d in zip(names, cols, dtypes, strict=False)
            }
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
            name=self.name,
            node_ids=list(self.ids),
            time=et,
            range=rng,
            fp_rssi=fp if has_fp else None,
            rx_rssi=rx if has_rx else None,
            configs=configs,
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
        from jaxcal.io.atomic import atomic_path

        ds = self.build_dataset()
        if ds is None:
            return False
        path = Path(path)
        with atomic_path(path) as tmp:
            with h5py.File(tmp, "w") as f:
                hdf5.write_open(f, ds)
                g = f.create_group("raw")
                lens = np.fromiter((len(r) for r in self.raw), np.int64, len(self.raw))
                off = np.zeros(lens.size + 1, np.int64)
                np.cumsum(lens, out=off[1:])
                big = {"compression": "gzip", "compression_opts": 1} if off[-1] > 4096 else {}
                g.create_dataset("frames", data=np.frombuffer(b"".join(self.raw), np.uint8), **big)
                g.create_dataset("offsets", data=off)
                g.create_dataset("time", data=np.asarray(self.raw_time, np.float64))
                g.attrs.update(
                    protocol=self.protocol,
                    time_source=self.time_source,
                    start_wall_time=self.start_wall_time,
                    self_id=self.self_id or "",
                    epoch_s=self.epoch_s,
                    placeholder_poses=int(not hasattr(ds, "node_ids")),
                    decoder_stats=json.dumps(self.decoder.stats.as_dict()),
                )
        sync_dir(path)
        return True

    def summary(self) -> dict:
        """Counters for `--json` and the status line."""
        s = self.decoder.stats.as_dict()
        s.update(
            ranges=self.n_ranges,
            negative_ranges=self.negative_ranges,
            duplicates=self.duplicates,
            nodes=len(self.ids),
            format=self.kind(),
            protocol=self.protocol,
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


def replay(
    path: str | os.PathLike,
    protocol: str | None,
    rec_kwargs: dict,
    rate: float = 10.0,
    on_flush: Callable[[Recording], None] | None = None,
    flush_s: float = 1.0,
) -> Recording:
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
        if sp is None:
            raise JaxcalError(f"{p}: the file names no protocol; cannot replay it")
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
        self.rec, self.on_flush, self.flush_s = rec, on_flush, flush_s
        self.next: float | None = None

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
