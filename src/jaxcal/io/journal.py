"""The recorder's append-only journal: every decoded frame goes to the kernel as soon as it is decoded.

Layout: ``JXCJRNL1``, u32 header length, a JSON header (protocol, self_id, time_source, start_wall_time,
port, baud), then one record per validated raw frame: ``u32 length, f64 time [s], payload, u32 crc32``
(little-endian). Records are written with `os.write` on an ``O_APPEND`` descriptor (no user-space
buffer): a frame handed to `append`/`extend` survives a SIGKILL of the process the moment the call
returns; `sync` (fsync, called on the flush period) protects it against a power loss too. A kill can
only tear the last record, which `read_journal` detects by its length or CRC and drops.

Recovery of an interrupted recording: ``jaxcal record --replay OUT.h5.journal -o OUT.h5``.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path

from jaxcal.errors import JaxcalError

__all__ = ["JOURNAL_MAGIC", "JournalWriter", "read_journal", "describe_journal", "write_all", "sync_dir"]

JOURNAL_MAGIC = b"JXCJRNL1"
_REC = struct.Struct("<Id")


def write_all(fd: int, data: bytes) -> None:
    """`os.write` until every byte is with the kernel (a regular file may take a write in parts)."""
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def sync_dir(path: str | os.PathLike) -> None:
    """fsync the folder holding `path`, so that a new or renamed entry survives a power loss."""
    try:
        fd = os.open(Path(path).resolve().parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some file systems refuse fsync on folders: nothing more can be done
        pass
    finally:
        os.close(fd)


def open_exclusive(path: str | os.PathLike) -> int:
    """A new file for appending without a user-space buffer; never opens an existing one."""
    return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, 0o644)


def _record(raw: bytes, t: float) -> bytes:
    return _REC.pack(len(raw), t) + raw + struct.pack("<I", zlib.crc32(raw))


class JournalWriter:
    """Append-only, write-through journal of raw frames (see the module docstring).

    Args:
        path: the journal file; it must not exist (an existing one is an unrecovered recording).
        header: JSON-able dict written first.
    """

    def __init__(self, path: str | os.PathLike, header: dict) -> None:
        self.path = Path(path)
        try:
            self._fd = open_exclusive(self.path)
        except FileExistsError:
            raise FileExistsError(f"{self.path}: exists (an unrecovered recording?)") from None
        self.frames = 0
        h = json.dumps(header).encode()
        write_all(self._fd, JOURNAL_MAGIC + struct.pack("<I", len(h)) + h)
        self.sync()
        sync_dir(self.path)

    def append(self, raw: bytes, t: float) -> None:
        """Hand one frame record to the kernel now."""
        write_all(self._fd, _record(raw, t))
        self.frames += 1

    def extend(self, raws: list[bytes], t: float) -> None:
        """Hand several frames received at the same time `t` [s] to the kernel in one write."""
        if raws:
            write_all(self._fd, b"".join(_record(r, t) for r in raws))
            self.frames += len(raws)

    def sync(self) -> None:
        """fsync: the records written so far survive a power loss."""
        if self._fd >= 0:
            os.fsync(self._fd)

    flush = sync  # the name of the buffered writer this one replaced

    @property
    def closed(self) -> bool:
        return self._fd < 0

    def close(self) -> None:
        """fsync and close."""
        if self._fd >= 0:
            self.sync()
            os.close(self._fd)
            self._fd = -1


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


def describe_journal(path: str | os.PathLike) -> str:
    """One phrase for messages: ``"412 frames over 41.2 s, protocol nlink, started ..."``."""
    try:
        header, records, torn = read_journal(path)
    except (JaxcalError, OSError) as e:
        return f"unreadable: {' '.join(str(e).split())}"
    span = records[-1][0] - records[0][0] if records else 0.0
    text = f"{len(records)} frames over {span:.1f} s, protocol {header.get('protocol', '?')}"
    if header.get("start_wall_time"):
        text += f", started {header['start_wall_time']}"
    if torn:
        text += f", a torn last record of {torn} B (dropped on recovery)"
    return text
