"""Encoders for the serial formats: build valid NLink frames, DWM1001 TLV responses and shell lines.

They take raw wire units (mm, raw RSSI bytes, mV), so that decode(encode(x)) can be checked exactly.
Used by the tests, the fuzz benchmark and device simulators; not needed to record.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

__all__ = [
    "with_checksum",
    "nodeframe3",
    "nodeframe5",
    "aoa_nodeframe0",
    "nodeframe2",
    "nodeframe4",
    "tagframe0",
    "anchorframe0",
    "unknown_frame",
    "loc_get_tag",
    "loc_get_anchor",
    "lec_line",
    "les_line",
]


def _i24(v: int) -> bytes:
    if not -(1 << 23) <= v < (1 << 23):
        raise ValueError(f"int24 out of range: {v}")
    return (v & 0xFFFFFF).to_bytes(3, "little")


def with_checksum(body: bytes) -> bytes:
    """Append the NLink checksum byte (sum of all bytes mod 256)."""
    return bytes(body) + bytes([sum(body) & 0xFF])


def _var_frame(mark: int, head: bytes, blocks: bytes) -> bytes:
    L = 4 + len(head) + len(blocks) + 1
    return with_checksum(bytes([0x55, mark]) + struct.pack("<H", L) + head + blocks)


def nodeframe3(
    role: int,
    ident: int,
    local_time: int,
    system_time: int,
    voltage_mv: int,
    nodes: Sequence[tuple[int, int, int, int, int]],
    reserved: bytes = bytes(4),
) -> bytes:
    """NodeFrame3 (0x55 0x05). nodes: (role, id, dis_mm, fp_rssi_byte, rx_rssi_byte) each."""
    head = (
        struct.pack("<BBII", role, ident, local_time, system_time)
        + reserved
        + struct.pack("<HB", voltage_mv, len(nodes))
    )
    blocks = b"".join(bytes([r, i]) + _i24(d) + bytes([fp, rx]) for r, i, d, fp, rx in nodes)
    return _var_frame(0x05, head, blocks)


def nodeframe5(
    role: int,
    ident: int,
    local_time: int,
    system_time: int,
    voltage_mv: int,
    nodes: Sequence[tuple[int, int, int, int, int]],
) -> bytes:
    """NodeFrame5 (0x55 0x08): NodeFrame3 with u32 ids."""
    head = (
        struct.pack("<BIII", role, ident, local_time, system_time)
        + bytes(4)
        + struct.pack("<HB", voltage_mv, len(nodes))
    )
    blocks = b"".join(struct.pack("<BI", r, i) + _i24(d) + bytes([fp, rx]) for r, i, d, fp, rx in nodes)
    return _var_frame(0x08, head, blocks)


def aoa_nodeframe0(
    role: int,
    ident: int,
    local_time: int,
    system_time: int,
    voltage_mv: int,
    nodes: Sequence[tuple[int, int, int, int, int, int]],
) -> bytes:
    """AOA NodeFrame0 (0x55 0x07). nodes: (role, id, dis_mm, angle_centideg, fp_byte, rx_byte)."""
    head = (
        struct.pack("<BBII", role, ident, local_time, system_time)
        + bytes(4)
        + struct.pack("<HB", voltage_mv, len(nodes))
    )
    blocks = b"".join(
        bytes([r, i]) + _i24(d) + struct.pack("<hBB", a, fp, rx) + bytes(2) for r, i, d, a, fp, rx in nodes
    )
    return _var_frame(0x07, head, blocks)


def nodeframe2(
    role: int,
    ident: int,
    system_time: int,
    local_time: int,
    voltage_mv: int,
    pos_mm: Sequence[int],
    nodes: Sequence[tuple[int, int, int, int, int, int]],
) -> bytes:
    """NodeFrame2 (0x55 0x04) with zero velocity/IMU. nodes: (role, id, dis_mm, fp, rx, node_time)."""
    head = bytearray(115)  # bytes 4..118
    head[0], head[1] = role, ident
    struct.pack_into("<I", head, 2, system_time)
    for k in range(3):
        head[9 + 3 * k : 12 + 3 * k] = _i24(pos_mm[k])
    struct.pack_into("<4f", head, 78, 1.0, 0.0, 0.0, 0.0)
    struct.pack_into("<I", head, 98, local_time)
    struct.pack_into("<HB", head, 112, voltage_mv, len(nodes))
    blocks = b"".join(
        bytes([r, i]) + _i24(d) + struct.pack("<BBI", fp, rx, t) + bytes(2) for r, i, d, fp, rx, t in nodes
    )
    return _var_frame(0x04, bytes(head), blocks)


def nodeframe4(
    role: int,
    ident: int,
    local_time: int,
    system_time: int,
    voltage_mv: int,
    tags: Sequence[tuple[int, int, Sequence[tuple[int, int]]]],
) -> bytes:
    """NodeFrame4 (0x55 0x06). tags: (tag_id, voltage_byte (V*20), [(anchor_id, dis_mm), ...])."""
    head = (
        struct.pack("<BBII", role, ident, local_time, system_time)
        + bytes(4)
        + struct.pack("<HB", voltage_mv, len(tags))
    )
    blocks = b"".join(
        bytes([tid, 0, 0, tv, len(anchors)]) + b"".join(bytes([a]) + _i24(d) for a, d in anchors)
        for tid, tv, anchors in tags
    )
    return _var_frame(0x06, head, blocks)


def tagframe0(
    ident: int,
    role: int,
    dis_mm: Sequence[int],
    local_time: int,
    system_time: int,
    voltage_mv: int,
    pos_mm: Sequence[int] = (0, 0, 0),
) -> bytes:
    """TagFrame0 (0x55 0x01, 128 B). dis_mm: 8 distances to anchors A0..A7 (0 = none)."""
    b = bytearray(127)
    b[0:4] = bytes([0x55, 0x01, ident, role])
    for k in range(3):
        b[4 + 3 * k : 7 + 3 * k] = _i24(pos_mm[k])
    for k in range(8):
        b[22 + 3 * k : 25 + 3 * k] = _i24(dis_mm[k])
    struct.pack_into("<4f", b, 88, 1.0, 0.0, 0.0, 0.0)
    struct.pack_into("<II", b, 108, local_time, system_time)
    struct.pack_into("<H", b, 120, voltage_mv)
    return with_checksum(bytes(b))


def anchorframe0(
    slots: Sequence[tuple[int, int, Sequence[int], Sequence[int]]],
    local_time: int,
    system_time: int,
    voltage_mv: int,
    ident: int = 0,
    role: int = 3,
    filler: int = 0xAB,
) -> bytes:
    """AnchorFrame0 (0x55 0x00, 896 B, tail 0xEE). slots: (id, role, pos_mm[3], dis_cm[8]), up to 30.

    Unused slots get id 0xFF and `filler` bytes (real frames carry leftovers there)."""
    b = bytearray([filler]) * 896
    b[0:2] = b"\x55\x00"
    for s in range(30):
        o = 2 + 27 * s
        if s < len(slots):
            sid, srole, pos, dis = slots[s]
            b[o : o + 2] = bytes([sid, srole])
            for k in range(3):
                b[o + 2 + 3 * k : o + 5 + 3 * k] = _i24(pos[k])
            struct.pack_into("<8H", b, o + 11, *dis)
        else:
            b[o] = 0xFF
    b[812:879] = bytes(67)
    struct.pack_into("<I", b, 879, local_time)
    b[883:887] = bytes(4)
    struct.pack_into("<HI", b, 887, voltage_mv, system_time)
    b[893], b[894], b[895] = ident, role, 0xEE
    return bytes(b)


def unknown_frame(mark: int, payload: bytes) -> bytes:
    """A frame with an unknown function mark, a u16 length and a good checksum."""
    return with_checksum(bytes([0x55, mark]) + struct.pack("<H", len(payload) + 5) + payload)


def _pos13(p_mm: Sequence[int], qf: int) -> bytes:
    return struct.pack("<iiiB", *p_mm, qf)


def loc_get_tag(pos_mm: Sequence[int], qf: int, anchors: Sequence[tuple[int, int, int, Sequence[int], int]]) -> bytes:
    """dwm_loc_get response of a tag. anchors: (addr u16, dist_mm, dist_qf, pos_mm[3], pos_qf)."""
    items = b"".join(struct.pack("<HIB", a, d, q) + _pos13(p, pq) for a, d, q, p, pq in anchors)
    return b"\x40\x01\x00\x41\x0d" + _pos13(pos_mm, qf) + bytes([0x49, 1 + 20 * len(anchors), len(anchors)]) + items


def loc_get_anchor(pos_mm: Sequence[int], qf: int, tags: Sequence[tuple[int, int, int]]) -> bytes:
    """dwm_loc_get response of an anchor (u64 addresses). tags: (addr u64, dist_mm, qf)."""
    items = b"".join(struct.pack("<QIB", a, d, q) for a, d, q in tags)
    return b"\x40\x01\x00\x41\x0d" + _pos13(pos_mm, qf) + bytes([0x48, 1 + 13 * len(tags), len(tags)]) + items


def lec_line(
    anchors: Sequence[tuple[str, Sequence[float], float]], pos: Sequence[float] | None = None, qf: int = 0
) -> bytes:
    """Shell ``lec`` line with CRLF. anchors: (id 4-hex, (x, y, z) m, dist m)."""
    parts = [f"DIST,{len(anchors)}"]
    for k, (aid, p, d) in enumerate(anchors):
        parts.append(f"AN{k},{aid},{p[0]:.2f},{p[1]:.2f},{p[2]:.2f},{d:.2f}")
    if pos is not None:
        parts.append(f"POS,{pos[0]:.2f},{pos[1]:.2f},{pos[2]:.2f},{qf}")
    return (",".join(parts) + "\r\n").encode()


def les_line(
    anchors: Sequence[tuple[str, Sequence[float], float]], le_us: int, est: Sequence[float] | None = None, qf: int = 0
) -> bytes:
    """Shell ``les`` line with CRLF."""
    toks = [f"{aid}[{p[0]:.2f},{p[1]:.2f},{p[2]:.2f}]={d:.2f}" for aid, p, d in anchors]
    toks.append(f"le_us={le_us}")
    if est is not None:
        toks.append(f"est[{est[0]:.2f},{est[1]:.2f},{est[2]:.2f},{qf}]")
    return (" ".join(toks) + "\r\n").encode()


# ------------------------------------------------------------------------------- random test streams


def random_nlink_frame(rng) -> bytes:
    """A random valid NLink frame of a random decodable type (or an unknown mark). `rng`: random.Random."""
    kind = rng.randrange(9)
    t = rng.randrange(1 << 32)
    volt = rng.randrange(3000, 5200)

    def nodes(k, ids=256):
        return [
            (rng.randrange(3), rng.randrange(ids), rng.randrange(-500, 60000), rng.randrange(256), rng.randrange(256))
            for _ in range(k)
        ]

    if kind <= 1:
        return nodeframe3(
            rng.randrange(3), rng.randrange(256), t, rng.randrange(1 << 32), volt, nodes(rng.randrange(9))
        )
    if kind == 2:
        return nodeframe5(rng.randrange(3), rng.randrange(1 << 32), t, t, volt, nodes(rng.randrange(6), 1 << 32))
    if kind == 3:
        return aoa_nodeframe0(
            2,
            rng.randrange(256),
            t,
            0,
            volt,
            [n[:3] + (rng.randrange(-18000, 18000),) + n[3:] for n in nodes(rng.randrange(6))],
        )
    if kind == 4:
        return nodeframe2(
            2,
            rng.randrange(256),
            t,
            t,
            volt,
            [rng.randrange(-9000, 9000) for _ in range(3)],
            [n + (t,) for n in nodes(rng.randrange(5))],
        )
    if kind == 5:
        tags = [
            (rng.randrange(256), rng.randrange(256), [(a, rng.randrange(0, 30000)) for a in range(rng.randrange(5))])
            for _ in range(rng.randrange(4))
        ]
        return nodeframe4(1, rng.randrange(256), t, t, volt, tags)
    if kind == 6:
        return tagframe0(
            rng.randrange(256), 2, [rng.choice((0, rng.randrange(1, 30000))) for _ in range(8)], t, t, volt
        )
    if kind == 7:
        slots = [
            (
                rng.randrange(255),
                2,
                [rng.randrange(-9000, 9000) for _ in range(3)],
                [rng.randrange(0, 3000) for _ in range(8)],
            )
            for _ in range(rng.randrange(4))
        ]
        return anchorframe0(slots, t, t, volt, filler=rng.randrange(256))
    return unknown_frame(rng.randrange(0x0A, 0x40), bytes(rng.randrange(256) for _ in range(rng.randrange(40))))


def corrupt(frame: bytes, rng) -> bytes:
    """Flip one bit of `frame` such that validation must reject it (AnchorFrame0 has no checksum, so
    only its header, mark or tail byte is hit)."""
    b = bytearray(frame)
    if b[1] == 0x00 and len(b) == 896:
        i = rng.choice((0, 1, 895))
    else:
        i = rng.randrange(len(b))
    b[i] ^= 1 << rng.randrange(8)
    return bytes(b)


def hostile_stream(
    rng, n_frames: int, p_corrupt: float = 0.2, p_garbage: float = 0.3, max_garbage: int = 64
) -> tuple[bytes, list[bytes]]:
    """A byte stream of random valid frames, bit-flipped frames and random garbage (0x55 included).

    Returns:
        (stream, valid): the bytes and the list of the valid frames in it, in order.
    """
    out, valid = bytearray(), []
    for _ in range(n_frames):
        if rng.random() < p_garbage:
            out += bytes(rng.randrange(256) for _ in range(rng.randrange(1, max_garbage)))
        f = random_nlink_frame(rng)
        if rng.random() < p_corrupt:
            out += corrupt(f, rng)
        else:
            out += f
            valid.append(f)
    return bytes(out), valid
