"""Qorvo/Decawave DWM1001 (PANS R2) UART output: TLV responses and shell lines, as pure functions on
bytes plus incremental stream decoders.

Formats and validation rules follow `shared/protocols/SPEC.md` section 2.

TLV (generic mode) has no sync byte, no checksum and no overall length, so a response is recognised by
its structure: a status item ``40 01 err`` then items whose lengths must match their type (0x41: 13;
0x49: 1 + 20 cnt; 0x48: 1 + 13 cnt or 1 + 7 cnt; 0x56: 1 + 16 cnt; 0x4E: 8). A response ends after a
terminal item (0x48, 0x49, 0x56, 0x4E, 0x5A), before the next status item, before an item of a type
this reader does not know (the bytes from there on are hunted as garbage), or at `finish()` (the
recorder calls it at each poll deadline). On a broken response only its first byte is dropped and the
hunt for ``40 01`` starts again.

Shell mode is line based: lines are split on ``\\n``; over-long lines (> 1 KiB), lines with non-ASCII or
control bytes, and ``lec``/``les``/``lep`` lines that break their layout are rejected and counted (no
salvage of partial lines); prompts, echoes and empty lines are ignored; firmware log lines are kept as
``"log"`` frames and other text as ``"unknown"`` frames.
"""

from __future__ import annotations

import math
import re
import struct

from jaxcal.io.serial.frames import DecoderStats, Frame, Range

__all__ = [
    "decode_tlv_response",
    "parse_shell_line",
    "TLVDecoder",
    "ShellDecoder",
    "decode_tlv",
    "decode_shell",
    "FrameError",
    "MAX_LINE",
]

ERR_CODES = {
    0: "ok",
    1: "unknown command or broken TLV frame",
    2: "internal error",
    3: "invalid parameter",
    4: "busy",
    5: "operation not permitted",
}
_ITEMS = (0x41, 0x48, 0x49, 0x4E, 0x56, 0x5A)
_TERMINAL = (0x48, 0x49, 0x4E, 0x56, 0x5A)
MAX_LINE = 1024


class FrameError(ValueError):
    """A complete TLV response or shell line broke its layout rules."""


# ------------------------------------------------------------------------------------------------ TLV


def _pos(b: bytes, o: int) -> tuple[tuple[float, float, float], int]:
    x, y, z, qf = struct.unpack_from("<iiiB", b, o)
    return (x / 1000.0, y / 1000.0, z / 1000.0), qf


def _item_ok(t: int, value: bytes | bytearray) -> bool:
    n = len(value)
    if t == 0x41:
        return n == 13
    if t == 0x4E:
        return n == 8
    if t == 0x5A:
        return True
    if n < 1:
        return False
    cnt = value[0]
    if t == 0x49:
        return n == 1 + 20 * cnt
    if t == 0x56:
        return n == 1 + 16 * cnt
    if t == 0x48:
        return n == 1 if cnt == 0 else (n - 1) % cnt == 0 and (n - 1) // cnt in (13, 7)
    return False


def _decode_items(raw: bytes, self_id: str | None) -> Frame:
    err = raw[2]
    if err != 0:
        return Frame("error", raw, {"err": err, "message": ERR_CODES.get(err, "unknown")})
    fields: dict = {"err": 0}
    ranges: list[Range] = []
    kind = "status"
    o = 3
    while o < len(raw):
        t, n = raw[o], raw[o + 1]
        v = raw[o + 2 : o + 2 + n]
        if t == 0x41:
            fields["position"], fields["qf"] = _pos(v, 0)
            kind = "pos_get" if kind == "status" else kind
        elif t == 0x49:
            me = self_id or "tag"
            anchors = []
            for k in range(v[0]):
                e = 1 + 20 * k
                addr, dist, dqf = struct.unpack_from("<HIB", v, e)
                p, pqf = _pos(v, e + 7)
                aid = f"{addr:04X}"
                anchors.append(
                    {"addr": addr, "id": aid, "dist": dist / 1000.0, "qf": dqf, "position": p, "pos_qf": pqf}
                )
                ranges.append(Range(me, aid, dist / 1000.0, math.nan, math.nan, "tag", "anchor"))
            fields["anchors"] = tuple(anchors)
            kind = "loc_get"
        elif t == 0x48:
            me = self_id or "anchor"
            size = 13 if v[0] == 0 or (n - 1) // v[0] == 13 else 7
            tags = []
            for k in range(v[0]):
                e = 1 + size * k
                addr = int.from_bytes(v[e : e + size - 5], "little")
                dist, dqf = struct.unpack_from("<IB", v, e + size - 5)
                tid = f"{addr & 0xFFFF:04X}"  # the 16-bit short id, as the shell prints it
                tags.append({"addr": addr, "id": tid, "dist": dist / 1000.0, "qf": dqf})
                ranges.append(Range(me, tid, dist / 1000.0, math.nan, math.nan, "anchor", "tag"))
            fields["tags"] = tuple(tags)
            kind = "loc_get_anchor"
        elif t == 0x56:
            anchors = []
            for k in range(v[0]):
                e = 1 + 16 * k
                aid, x, y, z, rssi, flags = struct.unpack_from("<HiiibB", v, e)
                anchors.append(
                    {
                        "id": f"{aid:04X}",
                        "position": (x / 1000.0, y / 1000.0, z / 1000.0),
                        "rssi": rssi,
                        "seat": flags & 0x1F,
                        "neighbor_network": bool(flags & 0x20),
                    }
                )
            fields["anchor_list"] = tuple(anchors)
            kind = "anchor_list_get"
        elif t == 0x4E:
            fields["node_id"] = int.from_bytes(v, "little")
            kind = "node_id_get"
        elif t == 0x5A:
            fields["status"] = bytes(v)
            kind = "status_get"
        o += 2 + n
    return Frame(kind, raw, fields, tuple(ranges))


def decode_tlv_response(raw: bytes, self_id: str | None = None) -> Frame:
    """Decode one complete DWM1001 TLV response (status item first).

    Args:
        raw: the response bytes, e.g. the 81 bytes answered to ``dwm_loc_get`` (``0C 00``).
        self_id: id of the module that answered (it is not in the response); default ``"tag"`` for a
            tag's 0x49 distances, ``"anchor"`` for an anchor's 0x48 distances.

    Returns:
        A `Frame` of type ``loc_get`` (tag), ``loc_get_anchor``, ``pos_get``, ``anchor_list_get``,
        ``node_id_get``, ``status_get``, ``status`` (status only) or ``error`` (err != 0).
        Positions are in metres, distances in metres, anchor ids 4 uppercase hex digits.

    Raises:
        FrameError: not a status item first, an item length inconsistent with its type, trailing bytes.
    """
    raw = bytes(raw)
    if len(raw) < 3 or raw[0] != 0x40 or raw[1] != 0x01 or raw[2] > 5:
        raise FrameError("TLV response must start with the status item 40 01 <err 0..5>")
    if raw[2] != 0 and len(raw) != 3:
        raise FrameError("TLV error response carries only its status item")
    o = 3
    while o < len(raw):
        if o + 2 > len(raw):
            raise FrameError("TLV response: truncated item header")
        t, n = raw[o], raw[o + 1]
        if t not in _ITEMS:
            raise FrameError(f"TLV response: unknown item type 0x{t:02x}")
        if o + 2 + n > len(raw) or not _item_ok(t, raw[o + 2 : o + 2 + n]):
            raise FrameError(f"TLV response: item 0x{t:02x} has an inconsistent length {n}")
        o += 2 + n
    return _decode_items(raw, self_id)


_MORE, _BAD, _FAIL = -1, -2, -3


class TLVDecoder:
    """Incremental decoder of a stream of DWM1001 TLV responses: `feed(bytes) -> list[Frame]`.

    Call `finish()` at each poll deadline (and at end of stream) to close a response that can only end
    by silence (e.g. ``pos_get``) and to drop incomplete bytes.
    """

    protocol = "dwm1001-tlv"

    def __init__(self, self_id: str | None = None) -> None:
        self.self_id = self_id
        self._buf = bytearray()
        self.stats = DecoderStats()

    @property
    def pending(self) -> int:
        """Bytes held back waiting for more."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Frame]:
        """Add bytes; returns the responses they completed."""
        self.stats.bytes_fed += len(data)
        self._buf += data
        return self._run(False)

    def finish(self) -> list[Frame]:
        """End of a response window or of the stream: resolve everything pending."""
        return self._run(True)

    def discard(self) -> int:
        """Drop the pending bytes (the link broke mid-response), counted as skipped; returns how many."""
        n = len(self._buf)
        self.stats.bytes_skipped += n
        self._buf.clear()
        return n

    def _candidate(self, buf: bytearray, p: int, final: bool) -> int:
        """End offset of a response starting at p, or _MORE / _BAD / _FAIL."""
        n = len(buf)
        if n - p < 3:
            return _BAD if final else _MORE
        if buf[p + 1] != 0x01 or buf[p + 2] > 5:
            return _BAD
        if buf[p + 2] != 0:
            return p + 3
        q = p + 3
        while True:
            if q >= n:
                return q if final else _MORE
            t = buf[q]
            if t not in _ITEMS:  # 0x40 (next response), garbage or an unknown item: the response ends here
                return q
            if q + 2 > n:
                return _BAD if final else _MORE
            L = buf[q + 1]
            if q + 2 + L > n:
                return _BAD if final else _MORE
            if not _item_ok(t, buf[q + 2 : q + 2 + L]):
                return _FAIL
            q += 2 + L
            if t in _TERMINAL:
                return q

    def _run(self, final: bool) -> list[Frame]:
        buf, st, out = self._buf, self.stats, []
        pos, end = 0, len(buf)
        while pos < end:
            p = buf.find(0x40, pos)
            if p < 0:
                st.bytes_skipped += end - pos
                pos = end
                break
            st.bytes_skipped += p - pos
            pos = p
            e = self._candidate(buf, p, final)
            if e == _MORE:
                break
            if e < 0:
                if e == _FAIL:
                    st.checksum_failures += 1
                st.bytes_skipped += 1
                pos = p + 1
                continue
            frame = _decode_items(bytes(buf[p:e]), self.self_id)
            out.append(frame)
            st.frames += 1
            st.by_type[frame.type] += 1
            pos = e
        del buf[:pos]
        return out


# ---------------------------------------------------------------------------------------------- shell

_NUM = r"-?\d+(?:\.\d+)?"
_NUM_RE = re.compile(_NUM + r"\Z")
_INT_RE = re.compile(r"-?\d+\Z")
_HEX4_RE = re.compile(r"[0-9A-F]{4}\Z")
_LES_ANCHOR = re.compile(rf"([0-9A-F]{{4}})\[({_NUM}),({_NUM}),({_NUM})\]=({_NUM})\Z")
_LES_EST = re.compile(rf"est\[({_NUM}),({_NUM}),({_NUM}),(\d+)\]\Z")
_LES_HINT = re.compile(r"[0-9A-F]{4}\[")
_LOG_RE = re.compile(r"\[\d+\.\d+ [A-Z]{3}\]")
_PROMPT = "dwm>"
_ECHOES = {"lec", "les", "lep", "quit", "reset", "si", "help", "?", "av", "nmg", "nis", "la", "lb", "ut", "f"}


def _floats(parts) -> tuple[float, ...]:
    if not all(_NUM_RE.match(p) for p in parts):
        raise FrameError(f"not a number in {parts}")
    return tuple(float(p) for p in parts)


def _parse_lec(text: str, me: str):
    parts = text.split(",")
    if len(parts) < 2 or not parts[1].isdigit():
        raise FrameError("lec: bad anchor count")
    n = int(parts[1])
    if len(parts) < 2 + 6 * n:
        raise FrameError("lec: fewer anchor slots than announced")
    anchors, ranges = [], []
    for k in range(n):
        s = parts[2 + 6 * k : 8 + 6 * k]
        if s[0] != f"AN{k}" or not _HEX4_RE.match(s[1]):
            raise FrameError(f"lec: bad slot {k}")
        x, y, z, d = _floats(s[2:])
        anchors.append({"id": s[1], "position": (x, y, z), "dist": d})
        ranges.append(Range(me, s[1], d, math.nan, math.nan, "tag", "anchor"))
    fields: dict = {"anchors": tuple(anchors)}
    tail = parts[2 + 6 * n :]
    if tail:
        if len(tail) != 5 or tail[0] != "POS" or not _INT_RE.match(tail[4]):
            raise FrameError("lec: bad tail (expected nothing or POS,x,y,z,qf)")
        fields["position"], fields["qf"] = _floats(tail[1:4]), int(tail[4])
    return fields, tuple(ranges)


def _parse_lep(text: str):
    parts = text.split(",")
    if len(parts) == 5 and _INT_RE.match(parts[4]):
        return {"position": _floats(parts[1:4]), "qf": int(parts[4])}
    if len(parts) == 8 and parts[1].isdigit() and _INT_RE.match(parts[6]):  # passive listener (SPEC: LOW)
        return {
            "index": int(parts[1]),
            "tag": parts[2],
            "position": _floats(parts[3:6]),
            "qf": int(parts[6]),
            "extra": parts[7],
        }
    raise FrameError("lep: expected POS,x,y,z,qf")


def _parse_les(text: str, me: str):
    anchors: list[dict[str, object]] = []
    ranges: list[Range] = []
    fields: dict[str, object] = {}
    for tok in text.split():
        m = _LES_ANCHOR.match(tok)
        if m:
            aid = m.group(1)
            x, y, z, d = (float(m.group(i)) for i in range(2, 6))
            anchors.append({"id": aid, "position": (x, y, z), "dist": d})
            ranges.append(Range(me, aid, d, math.nan, math.nan, "tag", "anchor"))
        elif tok.startswith("le_us=") and tok[6:].isdigit() and "le_us" not in fields:
            fields["le_us"] = int(tok[6:])
        elif (m := _LES_EST.match(tok)) and "position" not in fields:
            fields["position"] = tuple(float(m.group(i)) for i in (1, 2, 3))
            fields["qf"] = int(m.group(4))
        else:
            raise FrameError(f"les: unexpected token {tok[:20]!r}")
    fields["anchors"] = tuple(anchors)
    return fields, tuple(ranges)


def _strip_prompt(text: str) -> str | None:
    """Remove prompts and echoed commands; None when nothing else is left."""
    text = text.strip()
    while text.startswith(_PROMPT):
        text = text[len(_PROMPT) :].lstrip()
    if not text or text in _ECHOES:
        return None
    for marker in ("DIST,", "POS,"):  # a data line with the echo of the command glued in front
        i = text.find(marker)
        if i > 0 and text[:i].strip() in _ECHOES:
            return text[i:]
    return text


def parse_shell_line(line: bytes, self_id: str | None = None) -> Frame | None:
    """Parse one DWM1001 shell line (without its ``\\n``).

    Args:
        line: the line bytes; a trailing ``\\r`` is ignored.
        self_id: id of the tag on the port (default ``"tag"``): the lines do not name it.

    Returns:
        A `Frame` of type ``lec`` (``DIST,<n>,...``), ``les``, ``lep`` (``POS,...``), ``log`` (firmware log) or
        ``unknown`` (other text, kept raw); None for lines to ignore (empty, prompt, echoed command).
        Distances and coordinates are in metres, ids 4 uppercase hex digits.

    Raises:
        FrameError: a line with non-ASCII or control characters, longer than `MAX_LINE`, or an
            ``lec``/``les``/``lep`` line that breaks its layout (e.g. the garbled lines seen at high rates).
    """
    raw = bytes(line).rstrip(b"\r")
    if len(raw) > MAX_LINE:
        raise FrameError("shell line too long")
    text = raw.decode("ascii", errors="replace")
    if any(c == "\ufffd" or ord(c) < 32 and c != "\t" or ord(c) == 127 for c in text):
        raise FrameError("shell line with non-ASCII or control characters")
    stripped = _strip_prompt(text)
    if stripped is None:
        return None
    text = stripped
    me = self_id or "tag"
    if text.startswith("DIST,") and text.split(",", 2)[1].isdigit():
        fields, ranges = _parse_lec(text, me)
        return Frame("lec", raw, fields, ranges)
    if text.startswith("POS,"):
        return Frame("lep", raw, _parse_lep(text))
    if "le_us=" in text or _LES_HINT.match(text):
        fields, ranges = _parse_les(text, me)
        return Frame("les", raw, fields, ranges)
    if _LOG_RE.match(text):
        return Frame("log", raw, {"text": text})
    return Frame("unknown", raw, {"text": text})


class ShellDecoder:
    """Incremental decoder of DWM1001 shell output: `feed(bytes) -> list[Frame]`, one frame per line.

    Over-long lines are discarded whole (counted in ``bytes_skipped``) however the stream is chunked.
    """

    protocol = "dwm1001-shell"

    def __init__(self, self_id: str | None = None) -> None:
        self.self_id = self_id
        self._buf = bytearray()
        self._discarding = False
        self.stats = DecoderStats()

    @property
    def pending(self) -> int:
        """Bytes of the current unfinished line."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Frame]:
        """Add bytes; returns the frames of the lines they completed."""
        self.stats.bytes_fed += len(data)
        out: list[Frame] = []
        buf = self._buf
        buf += data
        start = 0
        while True:
            i = buf.find(b"\n", start)
            if i < 0:
                break
            if self._discarding:
                self.stats.bytes_skipped += i - start + 1
                self._discarding = False
            else:
                self._line(bytes(buf[start:i]), out, True)
            start = i + 1
        del buf[:start]
        if self._discarding or len(buf) > MAX_LINE + 1:  # +1: a trailing \r is not part of the line
            if not self._discarding:
                self.stats.checksum_failures += 1
            self.stats.bytes_skipped += len(buf)
            buf.clear()
            self._discarding = True
        return out

    def finish(self) -> list[Frame]:
        """End of stream: an unterminated last line is parsed as a line."""
        out: list[Frame] = []
        if self._buf and not self._discarding:
            self._line(bytes(self._buf), out, False)
        elif self._buf:
            self.stats.bytes_skipped += len(self._buf)
        self._buf.clear()
        self._discarding = False
        return out

    def discard(self) -> int:
        """Drop the unfinished line (the link broke or the recording stopped mid-line: parsing it could
        read a cut number as a whole one), counted as skipped; returns how many bytes."""
        n = len(self._buf)
        self.stats.bytes_skipped += n
        self._buf.clear()
        self._discarding = False
        return n

    def _line(self, line: bytes, out: list[Frame], terminated: bool) -> None:
        try:
            if len(line) > MAX_LINE + 1:
                raise FrameError("shell line too long")
            frame = parse_shell_line(line, self.self_id)
        except FrameError:
            self.stats.checksum_failures += 1
            self.stats.bytes_skipped += len(line) + terminated
            return
        if frame is not None:
            out.append(frame)
            self.stats.frames += 1
            self.stats.by_type[frame.type] += 1


def decode_tlv(data: bytes, self_id: str | None = None) -> tuple[list[Frame], DecoderStats]:
    """Decode a whole stream of TLV responses (pure function). Returns (frames, counters)."""
    d = TLVDecoder(self_id)
    return d.feed(data) + d.finish(), d.stats


def decode_shell(data: bytes, self_id: str | None = None) -> tuple[list[Frame], DecoderStats]:
    """Decode a whole shell-mode byte stream (pure function). Returns (frames, counters)."""
    d = ShellDecoder(self_id)
    return d.feed(data) + d.finish(), d.stats
