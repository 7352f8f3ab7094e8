"""Nooploop LinkTrack NLink binary frames: pure decoding functions and an incremental stream decoder.

Layouts, scales and the resynchronisation algorithm follow `shared/protocols/SPEC.md` sections 1.2-1.7
(restated from Nooploop's nlink_unpack and nlink_parser). In short: every frame starts 0x55 followed by a
function mark; variable frames carry their whole length as u16 at byte 2; the last byte is the sum of
all previous bytes mod 256, except AnchorFrame0 which ends in the constant 0xEE.

Stream rules (SPEC 1.7), implemented by `NLinkDecoder`:

* bytes before a 0x55 are garbage (skipped and counted);
* a candidate whose length is implausible (below its fixed part, above `MAX_LEN`, or, for frames with
  fixed-size node blocks, not ``fixed + 1 + node_size * count``) is rejected at once;
* on any rejection only the 0x55 byte is dropped, never the claimed length (a real frame may start
  inside a rejected region), so a corrupted length cannot make the reader skip real frames;
* a complete candidate of a known type is validated (checksum or tail, then a structural decode:
  node walks must end exactly at the checksum); failures are counted as ``checksum_failures``;
* an unknown function mark with a plausible u16 length and a good checksum is kept as an
  ``"unknown"`` frame (raw only), so the reader stays in sync across frame types it does not decode.

Guards beyond SPEC, against false frames in garbage, which the weak validation of some frame types
(fixed length, one sum byte or none) would otherwise let through with probability about 1/256 per false
header: TagFrame0 and AnchorFrame0 must carry role bytes below 16 (real roles are 0-6); TagFrame0's
quaternion must be unit (within 10 %) or all zero; and a frame of a weakly validated kind (unknown mark,
TagFrame0, AnchorFrame0) is rejected when a checksummed frame of a known type starts inside it, so a
real frame is never swallowed by a false one that happens to check out. What remains: a stray 0x55 in
garbage followed by an unknown mark, a plausible length and a matching sum (about 1 in 4096 stray 0x55
bytes) is kept as an ``"unknown"`` frame; such frames carry no ranges.
"""

from __future__ import annotations

import math
import struct
from typing import Any

from jaxcal.io.serial.frames import DecoderStats, Frame, Range

__all__ = [
    "MAX_LEN",
    "FRAME_TYPES",
    "ROLE_NAMES",
    "node_id",
    "checksum_ok",
    "decode_frame",
    "decode",
    "NLinkDecoder",
    "FrameError",
]

HEADER = 0x55
MAX_LEN = 4096  # SPEC 1.7.4: enough for a 255-node NodeFrame2 (3435 B); not a vendor number

# mark -> (name, fixed part size, node block size or None); the node count is the last fixed byte
VARIABLE: dict[int, tuple[str, int, int | None]] = {
    0x02: ("NodeFrame0", 11, None),
    0x03: ("NodeFrame1", 27, 20),
    0x04: ("NodeFrame2", 119, 13),
    0x05: ("NodeFrame3", 21, 7),
    0x06: ("NodeFrame4", 21, None),
    0x07: ("AOANodeFrame0", 21, 11),
    0x08: ("NodeFrame5", 24, 10),
    0x09: ("NodeFrame6", 14, None),
}
FIXED: dict[int, tuple[str, int]] = {0x00: ("AnchorFrame0", 896), 0x01: ("TagFrame0", 128)}
FRAME_TYPES: dict[int, str] = {**{m: v[0] for m, v in VARIABLE.items()}, **{m: v[0] for m, v in FIXED.items()}}
_WEAK = (0x00, 0x01)  # weakly validated known types (plus unknown marks): subject to the inner-frame veto

ROLE_NAMES = {0: "node", 1: "anchor", 2: "tag", 3: "console", 4: "dt_master", 5: "dt_slave", 6: "monitor"}
_ROLE_PREFIX = {0: "N", 1: "A", 2: "T", 3: "C", 4: "M", 5: "S", 6: "W"}


class FrameError(ValueError):
    """A complete candidate frame failed validation (checksum, tail, length or structure)."""


def node_id(role: int, ident: int) -> str:
    """String id of an NLink node: role letter + number, e.g. ``node_id(1, 3) == "A3"``.

    LinkTrack numbers anchors, tags and nodes separately (tag 1 and anchor 1 are different devices), so
    the role is part of the id. Unknown roles give ``"R<role>_<id>"``.
    """
    p = _ROLE_PREFIX.get(role)
    return f"{p}{ident}" if p else f"R{role}_{ident}"


def _role(role: int) -> str:
    return ROLE_NAMES.get(role, "unknown")


def _i24(b: bytes, o: int) -> int:
    return int.from_bytes(b[o : o + 3], "little", signed=True)


def _u16(b: bytes, o: int) -> int:
    return b[o] | (b[o + 1] << 8)


def _u32(b: bytes, o: int) -> int:
    return int.from_bytes(b[o : o + 4], "little")


def _rssi(x: int) -> float:
    return x / -2.0


def checksum_ok(raw: bytes) -> bool:
    """True when the last byte is the sum of all previous bytes mod 256 (AnchorFrame0: tail 0xEE)."""
    if len(raw) < 2:
        return False
    if raw[1] == 0x00 and len(raw) == 896:
        return raw[-1] == 0xEE
    return (sum(raw[:-1]) & 0xFF) == raw[-1]


# --------------------------------------------------------------------------------------------- decoding


def _ranging_nodes(raw, start, n, size, id_len, reporter, rep_role, angle=False, node_time=False):
    """Walk `n` fixed-size ranging node blocks (NodeFrame2/3/5, AOA NodeFrame0)."""
    nodes, ranges = [], []
    for k in range(n):
        o = start + size * k
        role = raw[o]
        ident = raw[o + 1] if id_len == 1 else _u32(raw, o + 1)
        o2 = o + 1 + id_len
        dis = _i24(raw, o2) / 1000.0
        node: dict[str, Any] = {"role": role, "id": ident, "dis": dis}
        if angle:
            node["angle"] = struct.unpack_from("<h", raw, o2 + 3)[0] / 100.0
            fp, rx = raw[o2 + 5], raw[o2 + 6]
        else:
            fp, rx = raw[o2 + 3], raw[o2 + 4]
        node["fp_rssi"], node["rx_rssi"] = _rssi(fp), _rssi(rx)
        if node_time:
            node["system_time"] = _u32(raw, o2 + 5)
        nodes.append(node)
        ranges.append(
            Range(reporter, node_id(role, ident), dis, node["fp_rssi"], node["rx_rssi"], _role(rep_role), _role(role))
        )
    return tuple(nodes), tuple(ranges)


def _dec_nodeframe3(raw: bytes, aoa: bool = False):
    role, ident = raw[4], raw[5]
    f: dict[str, object] = {
        "role": role,
        "id": ident,
        "local_time": _u32(raw, 6),
        "system_time": _u32(raw, 10),
        "voltage": _u16(raw, 18) / 1000.0,
    }
    nodes, ranges = _ranging_nodes(raw, 21, raw[20], 11 if aoa else 7, 1, node_id(role, ident), role, angle=aoa)
    f["nodes"] = nodes
    return f, ranges, f["local_time"]


def _dec_nodeframe5(raw: bytes):
    role, ident = raw[4], _u32(raw, 5)
    f: dict[str, object] = {
        "role": role,
        "id": ident,
        "local_time": _u32(raw, 9),
        "system_time": _u32(raw, 13),
        "voltage": _u16(raw, 21) / 1000.0,
    }
    nodes, ranges = _ranging_nodes(raw, 24, raw[23], 10, 4, node_id(role, ident), role)
    f["nodes"] = nodes
    return f, ranges, f["local_time"]


def _dec_nodeframe2(raw: bytes):
    role, ident = raw[4], raw[5]
    f: dict[str, object] = {
        "role": role,
        "id": ident,
        "system_time": _u32(raw, 6),
        "eop": tuple(raw[10 + i] / 100.0 for i in range(3)),
        "pos": tuple(_i24(raw, 13 + 3 * i) / 1000.0 for i in range(3)),
        "vel": tuple(_i24(raw, 22 + 3 * i) / 10000.0 for i in range(3)),
        "gyro": struct.unpack_from("<3f", raw, 40),
        "acc": struct.unpack_from("<3f", raw, 52),
        "angle": tuple(v / 100.0 for v in struct.unpack_from("<3h", raw, 76)),
        "quaternion": struct.unpack_from("<4f", raw, 82),
        "local_time": _u32(raw, 102),
        "voltage": _u16(raw, 116) / 1000.0,
    }
    nodes, ranges = _ranging_nodes(raw, 119, raw[118], 13, 1, node_id(role, ident), role, node_time=True)
    f["nodes"] = nodes
    return f, ranges, f["local_time"]


def _dec_nodeframe4(raw: bytes):
    role, ident = raw[4], raw[5]
    f: dict[str, object] = {
        "role": role,
        "id": ident,
        "local_time": _u32(raw, 6),
        "system_time": _u32(raw, 10),
        "voltage": _u16(raw, 18) / 1000.0,
    }
    end = len(raw) - 1
    o = 21
    tags, ranges = [], []
    for _ in range(raw[20]):
        if o + 5 > end:
            raise FrameError("NodeFrame4: tag block runs past the checksum")
        tid, tvolt, na = raw[o], raw[o + 3] / 20.0, raw[o + 4]
        o += 5
        if o + 4 * na > end:
            raise FrameError("NodeFrame4: anchor list runs past the checksum")
        anchors = {}
        for _a in range(na):
            aid, dis = raw[o], _i24(raw, o + 1) / 1000.0
            anchors[aid] = dis
            ranges.append(Range(node_id(2, tid), node_id(1, aid), dis, math.nan, math.nan, "tag", "anchor"))
            o += 4
        tags.append({"id": tid, "voltage": tvolt, "anchors": anchors})
    if o != end:
        raise FrameError(f"NodeFrame4: node walk ends at byte {o}, expected {end}")
    f["tags"] = tuple(tags)
    return f, tuple(ranges), f["local_time"]


def _dec_nodeframe1(raw: bytes):
    f: dict[str, object] = {
        "role": raw[4],
        "id": raw[5],
        "system_time": _u32(raw, 6),
        "local_time": _u32(raw, 10),
        "voltage": _u16(raw, 24) / 1000.0,
    }
    nodes = []
    for k in range(raw[26]):
        o = 27 + 20 * k
        nodes.append(
            {"role": raw[o], "id": raw[o + 1], "pos": tuple(_i24(raw, o + 2 + 3 * i) / 1000.0 for i in range(3))}
        )
    f["nodes"] = tuple(nodes)
    return f, (), f["local_time"]


def _dec_data(raw: bytes, id_len: int):
    """NodeFrame0 / NodeFrame6: data transmission blocks; the walk must end at the checksum."""
    fixed = 11 if id_len == 1 else 14
    f: dict[str, object] = {"role": raw[4], "id": raw[5] if id_len == 1 else _u32(raw, 5)}
    end = len(raw) - 1
    o = fixed
    nodes = []
    for _ in range(raw[fixed - 1]):
        if o + 3 + id_len > end:
            raise FrameError("data frame: node header runs past the checksum")
        role = raw[o]
        ident = raw[o + 1] if id_len == 1 else _u32(raw, o + 1)
        n = _u16(raw, o + 1 + id_len)
        o += 3 + id_len
        if o + n > end:
            raise FrameError("data frame: node data runs past the checksum")
        nodes.append({"role": role, "id": ident, "data": bytes(raw[o : o + n])})
        o += n
    if o != end:
        raise FrameError(f"data frame: node walk ends at byte {o}, expected {end}")
    f["nodes"] = tuple(nodes)
    return f, (), None


def _dec_tagframe0(raw: bytes):
    ident, role = raw[2], raw[3]
    if role >= 16:
        raise FrameError(f"TagFrame0: implausible role byte {role}")
    q = struct.unpack_from("<4f", raw, 88)
    qn = math.fsum(v * v for v in q)
    if not (0.81 <= qn <= 1.21 or raw[88:104] == bytes(16)):
        raise FrameError("TagFrame0: quaternion is neither unit nor zero")
    dis = tuple(_i24(raw, 22 + 3 * k) / 1000.0 for k in range(8))
    f: dict[str, object] = {
        "id": ident,
        "role": role,
        "pos": tuple(_i24(raw, 4 + 3 * i) / 1000.0 for i in range(3)),
        "vel": tuple(_i24(raw, 13 + 3 * i) / 10000.0 for i in range(3)),
        "dis": dis,
        "gyro": struct.unpack_from("<3f", raw, 46),
        "acc": struct.unpack_from("<3f", raw, 58),
        "angle": tuple(v / 100.0 for v in struct.unpack_from("<3h", raw, 82)),
        "quaternion": q,
        "local_time": _u32(raw, 108),
        "system_time": _u32(raw, 112),
        "eop": tuple(raw[117 + i] / 100.0 for i in range(3)),
        "voltage": _u16(raw, 120) / 1000.0,
    }
    me = node_id(role, ident)
    ranges = tuple(
        Range(me, node_id(1, k), d, math.nan, math.nan, _role(role), "anchor") for k, d in enumerate(dis) if d != 0
    )
    return f, ranges, f["local_time"]


def _dec_anchorframe0(raw: bytes):
    role = raw[894]
    if role >= 16:
        raise FrameError(f"AnchorFrame0: implausible role byte {role}")
    slots: list[dict[str, object]] = []
    ranges: list[Range] = []
    for s in range(30):
        o = 2 + 27 * s
        ident = raw[o]
        if ident == 0xFF:  # unused slot; its other bytes are not zero in real frames (SPEC 1.4)
            continue
        srole = raw[o + 1]
        if srole >= 16:
            raise FrameError(f"AnchorFrame0: implausible role byte {srole} in slot {s}")
        dis = tuple(_u16(raw, o + 11 + 2 * k) / 100.0 for k in range(8))
        slots.append(
            {"id": ident, "role": srole, "pos": tuple(_i24(raw, o + 2 + 3 * i) / 1000.0 for i in range(3)), "dis": dis}
        )
        me = node_id(srole, ident)
        ranges.extend(
            Range(me, node_id(1, k), d, math.nan, math.nan, _role(srole), "anchor") for k, d in enumerate(dis) if d != 0
        )
    f: dict[str, object] = {
        "nodes": tuple(slots),
        "local_time": _u32(raw, 879),
        "voltage": _u16(raw, 887) / 1000.0,
        "system_time": _u32(raw, 889),
        "id": raw[893],
        "role": role,
    }
    return f, tuple(ranges), f["local_time"]


_DECODERS = {
    0x00: _dec_anchorframe0,
    0x01: _dec_tagframe0,
    0x02: lambda r: _dec_data(r, 1),
    0x03: _dec_nodeframe1,
    0x04: _dec_nodeframe2,
    0x05: _dec_nodeframe3,
    0x06: _dec_nodeframe4,
    0x07: lambda r: _dec_nodeframe3(r, aoa=True),
    0x08: _dec_nodeframe5,
    0x09: lambda r: _dec_data(r, 4),
}


def _expected_length(raw) -> int | None:
    """The length a known frame must have from its header bytes, or None when undecidable/implausible."""
    mark = raw[1]
    if mark in FIXED:
        return FIXED[mark][1]
    name, fixed, node = VARIABLE[mark]
    if len(raw) < max(4, fixed):
        return None
    L = _u16(raw, 2)
    if L < fixed + 1 or L > MAX_LEN:
        return None
    if node is not None and L != fixed + 1 + node * raw[fixed - 1]:
        return None
    return L


def decode_frame(raw: bytes) -> Frame:
    """Decode one complete NLink frame.

    Args:
        raw: exactly one frame, header to checksum (bytes).

    Returns:
        The decoded `Frame` (type ``"unknown"`` with no fields for an unknown function mark whose length
        and checksum are right).

    Raises:
        FrameError: wrong header, wrong length, bad checksum or tail, or a broken node walk.
    """
    raw = bytes(raw)
    if len(raw) < 5 or raw[0] != HEADER:
        raise FrameError("not an NLink frame (header 0x55 and at least 5 bytes expected)")
    mark = raw[1]
    if mark not in FRAME_TYPES:
        if _u16(raw, 2) != len(raw):
            raise FrameError(f"unknown mark 0x{mark:02x}: length field {_u16(raw, 2)} != {len(raw)}")
        if not checksum_ok(raw):
            raise FrameError(f"unknown mark 0x{mark:02x}: bad checksum")
        return Frame("unknown", raw, {"mark": mark})
    name = FRAME_TYPES[mark]
    L = _expected_length(raw)
    if L != len(raw):
        raise FrameError(f"{name}: length {len(raw)} does not match its header (expected {L})")
    if not checksum_ok(raw):
        raise FrameError(f"{name}: bad {'tail byte' if mark == 0 else 'checksum'}")
    fields, ranges, t = _DECODERS[mark](raw)
    return Frame(name, raw, fields, ranges, t)


# ------------------------------------------------------------------------------------------ streaming

_MORE, _BAD, _FAIL, _OK = 0, 1, 2, 3


class NLinkDecoder:
    """Incremental NLink stream decoder: `feed(bytes) -> list[Frame]`, robust to any split of the stream.

    The decisions depend only on the bytes, never on how they were chunked, so feeding a stream in any
    pieces yields the same frames as feeding it at once (then `finish()`). Counters are in `stats`;
    every byte fed ends up in a frame, in `stats.bytes_skipped`, or in `pending` (waiting for more).
    """

    protocol = "nlink"

    def __init__(self) -> None:
        self._buf = bytearray()
        self.stats = DecoderStats()

    @property
    def pending(self) -> int:
        """Bytes held back because they may start a frame that is not complete yet."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Frame]:
        """Add bytes; returns the frames completed by them, in stream order."""
        self.stats.bytes_fed += len(data)
        self._buf += data
        return self._run(final=False)

    def finish(self) -> list[Frame]:
        """End of stream: resolve what is pending (incomplete candidates are dropped and counted)."""
        return self._run(final=True)

    def discard(self) -> int:
        """Drop the pending bytes (the link broke mid-frame), counted as skipped; returns how many."""
        n = len(self._buf)
        self.stats.bytes_skipped += n
        self._buf.clear()
        return n

    # A candidate at position p: (status, length, frame)
    def _known(self, buf: bytearray, p: int, final: bool, veto: bool = True):
        n = len(buf) - p
        mark = buf[p + 1]
        if mark in FIXED:
            L = FIXED[mark][1]
        else:
            _, fixed, node = VARIABLE[mark]
            if n < 4:
                return _MORE, 0, None
            L = buf[p + 2] | (buf[p + 3] << 8)
            if L < fixed + 1 or L > MAX_LEN:
                return _BAD, 0, None
            if node is not None:
                if n < fixed:
                    return _MORE, 0, None
                if L != fixed + 1 + node * buf[p + fixed - 1]:
                    return _BAD, 0, None
        if n < L:
            return _MORE, 0, None
        raw = bytes(buf[p : p + L])
        if not checksum_ok(raw):
            return _FAIL, 0, None
        try:
            fields, ranges, t = _DECODERS[mark](raw)
        except (FrameError, IndexError, struct.error):
            return _FAIL, 0, None
        if veto and mark in _WEAK:
            v = self._inner_frame(buf, p, L, final)
            if v != _BAD:
                return (_MORE, 0, None) if v == _MORE else (_FAIL, 0, None)
        return _OK, L, Frame(FRAME_TYPES[mark], raw, fields, ranges, t)

    def _inner_frame(self, buf: bytearray, p: int, L: int, final: bool) -> int:
        """_OK when a checksummed frame of a known type starts inside buf[p+1 : p+L]; _MORE if undecided."""
        q = p
        while True:
            q = buf.find(HEADER, q + 1, p + L)
            if q < 0:
                return _BAD
            if q + 1 >= len(buf):
                return _BAD if final else _MORE
            if buf[q + 1] in VARIABLE:
                s = self._known(buf, q, final, veto=False)[0]
                if s == _OK:
                    return _OK
                if s == _MORE and not final:
                    return _MORE

    def _unknown(self, buf: bytearray, p: int, final: bool):
        n = len(buf) - p
        if n < 4:
            return _MORE, 0, None
        L = buf[p + 2] | (buf[p + 3] << 8)
        if L < 5 or L > MAX_LEN:
            return _BAD, 0, None
        if n < L:
            return _MORE, 0, None
        raw = bytes(buf[p : p + L])
        if not checksum_ok(raw):
            return _BAD, 0, None
        v = self._inner_frame(buf, p, L, final)
        if v == _MORE:
            return _MORE, 0, None
        if v == _OK:
            return _BAD, 0, None
        return _OK, L, Frame("unknown", raw, {"mark": raw[1]})

    def _run(self, final: bool) -> list[Frame]:
        buf = self._buf
        st = self.stats
        out: list[Frame] = []
        pos = 0
        end = len(buf)
        while pos < end:
            p = buf.find(HEADER, pos)
            if p < 0:
                st.bytes_skipped += end - pos
                pos = end
                break
            st.bytes_skipped += p - pos
            pos = p
            if p + 1 >= end:
                status = _MORE
            elif buf[p + 1] in FRAME_TYPES:
                status, L, frame = self._known(buf, p, final)
            else:
                status, L, frame = self._unknown(buf, p, final)
            if status == _OK:
                out.append(frame)
                st.frames += 1
                st.by_type[frame.type] += 1
                pos = p + L
                continue
            if status == _MORE and not final:
                break
            if status == _FAIL:
                st.checksum_failures += 1
            st.bytes_skipped += 1  # drop only the header byte and hunt again (SPEC 1.7.6)
            pos = p + 1
        del buf[:pos]
        return out


def decode(data: bytes) -> tuple[list[Frame], DecoderStats]:
    """Decode a whole NLink byte stream (pure function). Returns (frames, counters)."""
    d = NLinkDecoder()
    frames = d.feed(data)
    frames += d.finish()
    return frames, d.stats
