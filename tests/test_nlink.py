"""NLink decoder: the SPEC vectors (read from ../shared/protocols, never copied), corruption, resync and
chunking properties."""

from __future__ import annotations

import random
import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import shared_path
from jaxcal.io.serial import encode as E
from jaxcal.io.serial import nlink
from jaxcal.io.serial.nlink import FrameError, NLinkDecoder, decode, decode_frame


def spec_vector(title: str) -> bytes:
    """The hex block that follows `title` in SPEC.md."""
    text = shared_path("protocols", "SPEC.md").read_text()
    i = text.index(title)
    m = re.search(r"```\n(.*?)```", text[i:], re.S)
    return bytes.fromhex(m.group(1))


def hex_file(name: str) -> bytes:
    return bytes.fromhex(shared_path("protocols", name).read_text())


def approx_seq(xs, ys, tol=1e-9):
    return len(xs) == len(ys) and all(abs(x - y) <= tol for x, y in zip(xs, ys, strict=False))


# ------------------------------------------------------------------------------------- SPEC vectors


def test_nodeframe3_vector():
    raw = spec_vector("**NodeFrame3** (50 B")
    f = decode_frame(raw)
    assert f.type == "NodeFrame3" and len(raw) == 50 and raw[-1] == 0x9A
    x = f.fields
    assert (x["role"], x["id"], x["local_time"], x["system_time"]) == (2, 1, 463352, 7262319)
    assert x["voltage"] == pytest.approx(4.954)
    nodes = [(n["role"], n["id"], n["dis"], n["fp_rssi"], n["rx_rssi"]) for n in x["nodes"]]
    assert nodes == [
        (1, 0, 2.850, -90.5, -79.5),
        (1, 1, 6.051, -91, -80),
        (1, 2, 7.304, -85, -79.5),
        (1, 3, 5.350, -92, -80),
    ]
    assert [(r.src, r.dst, r.src_role, r.dst_role) for r in f.ranges][0] == ("T1", "A0", "tag", "anchor")
    assert [r.range_m for r in f.ranges] == [2.850, 6.051, 7.304, 5.350]


def test_nodeframe5_vector_same_values_as_nodeframe3():
    f5 = decode_frame(spec_vector("**NodeFrame5** (65 B)"))
    f3 = decode_frame(spec_vector("**NodeFrame3** (50 B"))
    assert f5.type == "NodeFrame5" and len(f5.raw) == 65
    assert f5.fields == f3.fields
    assert f5.ranges == f3.ranges


def test_aoa_nodeframe0_vector():
    f = decode_frame(spec_vector("**AOA NodeFrame0** (66 B)"))
    x = f.fields
    assert f.type == "AOANodeFrame0"
    assert (x["role"], x["id"], x["local_time"], x["system_time"]) == (2, 0, 160702, 0)
    assert x["voltage"] == pytest.approx(4.847)
    got = [(n["id"], n["dis"], n["angle"], n["fp_rssi"], n["rx_rssi"]) for n in x["nodes"]]
    assert got == [
        (0, 0.767, 28.50, -81.5, -79.5),
        (1, 0.770, 1.73, -82, -79.5),
        (2, 1.004, 9.71, -82.5, -80),
        (3, 1.416, -49.67, -81.5, -80),
    ]


def test_nodeframe2_vector():
    f = decode_frame(spec_vector("**NodeFrame2** (172 B)"))
    x = f.fields
    assert f.type == "NodeFrame2"
    assert (x["system_time"], x["local_time"]) == (1926842, 9157)
    assert x["voltage"] == pytest.approx(4.973)
    assert x["pos"] == (2.782, -0.033, 1.000)
    assert approx_seq(x["vel"], (-0.0006, 0.0026, 0))
    assert approx_seq(x["gyro"], (0.02767, 0.00958, -0.04576), 1e-5)
    assert approx_seq(x["acc"], (0.224942, 9.73712, -0.05504), 1e-5)
    assert x["angle"] == (90.69, 91.93, -88.48)
    assert approx_seq(x["quaternion"], (0.691282, 0.694677, 0.154792, -0.110552), 1e-6)
    assert approx_seq(x["eop"], (0.06, 0.09, 2.55))
    got = [(n["id"], n["dis"], n["fp_rssi"], n["rx_rssi"], n["system_time"]) for n in x["nodes"]]
    assert got == [
        (0, 3.179, -88.5, -79.5, 1926822),
        (1, 5.548, -90, -80.5, 1926822),
        (2, 6.728, -101, -79.5, 1926822),
        (3, 4.651, -99, -80, 1926822),
    ]


def test_nodeframe4_stream_file():
    stream = hex_file("nodeframe4_stream.hex")
    assert len(stream) == 256
    frames, stats = decode(stream)
    assert [f.type for f in frames] == ["NodeFrame4"] * 4 and stats.bytes_skipped == 0
    first, last = frames[0].fields, frames[-1].fields
    assert (first["role"], first["id"], first["local_time"], first["system_time"]) == (1, 3, 105870, 105870)
    assert first["voltage"] == pytest.approx(4.456)
    assert [(t["id"], t["voltage"], t["anchors"]) for t in first["tags"]] == [
        (2, 4.40, {0: 2.445, 1: 1.748, 2: 2.038, 3: 1.709}),
        (5, 3.50, {0: 2.744, 1: 1.427, 2: 2.408, 3: 1.347}),
    ]
    assert last["local_time"] == 106020 and last["voltage"] == pytest.approx(4.44)
    assert [(t["id"], t["voltage"], list(t["anchors"].values())) for t in last["tags"]] == [
        (2, 4.45, [2.422, 1.729, 2.107, 1.762]),
        (5, 3.65, [2.701, 1.429, 2.378, 1.33]),
    ]
    assert (frames[0].ranges[0].src, frames[0].ranges[0].dst) == ("T2", "A0")
    # the same frames however the stream is split
    for cut in range(1, 256):
        d = NLinkDecoder()
        assert d.feed(stream[:cut]) + d.feed(stream[cut:]) + d.finish() == frames


def test_nodeframe1_vector():
    f = decode_frame(spec_vector("**NodeFrame1** (68 B)"))
    x = f.fields
    assert (x["role"], x["system_time"], x["local_time"]) == (3, 33000, 34304)
    assert x["voltage"] == pytest.approx(4.936)
    assert [(n["id"], n["pos"]) for n in x["nodes"]] == [(0, (2.911, 2.438, -0.101)), (2, (2.451, 2.373, -0.828))]
    assert f.ranges == ()


def test_data_frames_vectors():
    f0 = decode_frame(spec_vector("**NodeFrame0** (66 B)"))
    f6 = decode_frame(spec_vector("**NodeFrame6** (75 B)"))
    for f in (f0, f6):
        assert [len(n["data"]) for n in f.fields["nodes"]] == [9, 37]
        assert f.fields["nodes"][0]["data"] == bytes.fromhex("112233445566778899")
    assert f0.fields["nodes"] == f6.fields["nodes"]


def test_tagframe0_vector():
    f = decode_frame(spec_vector("**TagFrame0** (128 B)"))
    x = f.fields
    assert (x["id"], x["role"], x["local_time"], x["system_time"]) == (1, 2, 44556, 71627)
    assert x["voltage"] == pytest.approx(4.948)
    assert x["pos"] == (2.702, -0.091, 1.000)
    assert approx_seq(x["vel"], (-0.0038, -0.0006, 0))
    assert x["dis"] == (3.125, 5.539, 6.861, 4.684, 0, 0, 0, 0)
    assert x["angle"] == (144.49, 97.17, -14.68)
    assert approx_seq(x["eop"], (0.11, 0.16, 2.55))
    assert [(r.dst, r.range_m) for r in f.ranges] == [("A0", 3.125), ("A1", 5.539), ("A2", 6.861), ("A3", 4.684)]


def test_anchorframe0_file():
    raw = hex_file("anchorframe0.hex")
    assert len(raw) == 896 and raw[-1] == 0xEE and (sum(raw[:-1]) & 0xFF) == 0xDB
    f = decode_frame(raw)
    x = f.fields
    assert [(n["id"], n["role"], n["pos"], n["dis"]) for n in x["nodes"]] == [
        (0, 2, (2.895, 2.419, -0.263), (3.64, 3.34, 4.90, 4.93, 0, 0, 0, 0)),
        (2, 2, (2.435, 2.399, -1.117), (3.18, 2.98, 5.30, 5.31, 0, 0, 0, 0)),
    ]
    assert (x["local_time"], x["system_time"], x["id"], x["role"]) == (33313, 32000, 0, 3)
    assert x["voltage"] == pytest.approx(4.995)
    assert len(f.ranges) == 8 and f.ranges[0][:3] == ("T0", "A0", 3.64)
    bad = bytearray(raw)
    bad[-1] = 0xED
    with pytest.raises(FrameError):
        decode_frame(bytes(bad))


def test_encoders_reproduce_vectors():
    """The test encoders are checked against the vendor bytes, so streams built with them are real."""
    nf3 = spec_vector("**NodeFrame3** (50 B")
    nodes = [(1, 0, 2850, 181, 159), (1, 1, 6051, 182, 160), (1, 2, 7304, 170, 159), (1, 3, 5350, 184, 160)]
    assert E.nodeframe3(2, 1, 463352, 7262319, 4954, nodes, reserved=bytes([0, 0, 1, 2])) == nf3
    assert (
        E.nodeframe4(
            1,
            3,
            105870,
            105870,
            4456,
            [
                (2, 88, [(0, 2445), (1, 1748), (2, 2038), (3, 1709)]),
                (5, 70, [(0, 2744), (1, 1427), (2, 2408), (3, 1347)]),
            ],
        )[20:-1]
        == hex_file("nodeframe4_stream.hex")[20:63]
    )


# ---------------------------------------------------------------------------------------- corruption


def test_every_single_bit_flip_is_rejected():
    raw = spec_vector("**NodeFrame3** (50 B")
    for i in range(len(raw)):
        for bit in range(8):
            b = bytearray(raw)
            b[i] ^= 1 << bit
            with pytest.raises(FrameError):
                decode_frame(bytes(b))
            frames, stats = decode(bytes(b))
            assert frames == [], (i, bit)
            assert stats.bytes_skipped == len(raw)


def test_hostile_stream_resync():
    """SPEC 1.7: leading garbage, a false header with a plausible length, a bad checksum, an unknown
    mark, a truncated tail; split at random points."""
    nf3 = spec_vector("**NodeFrame3** (50 B")
    nf2 = spec_vector("**NodeFrame2** (172 B")
    tag = spec_vector("**TagFrame0** (128 B)")
    false_header = b"\x55\x05\x32\x00\x02"  # claims a 50-byte NodeFrame3, then real data follows
    bad_sum = nf3[:-1] + bytes([nf3[-1] ^ 0xFF])
    unknown = E.unknown_frame(0x0A, b"hello")
    stream = b"\x00\xff\x55garbage" + false_header + nf3 + bad_sum + nf2 + unknown + b"\x55\x55" + tag + nf3[:30]
    expect = [nf3, nf2, unknown, tag]
    rng = random.Random(7)
    for _ in range(50):
        d = NLinkDecoder()
        out, i = [], 0
        while i < len(stream):
            k = rng.randrange(1, 40)
            out += d.feed(stream[i : i + k])
            i += k
        out += d.finish()
        assert [f.raw for f in out] == expect
        assert [f.type for f in out] == ["NodeFrame3", "NodeFrame2", "unknown", "TagFrame0"]
        assert d.stats.checksum_failures >= 1
        assert d.stats.bytes_fed == sum(len(f.raw) for f in out) + d.stats.bytes_skipped
        assert d.stats.by_type == {"NodeFrame3": 1, "NodeFrame2": 1, "unknown": 1, "TagFrame0": 1}


def test_nodeframe4_walk_must_end_at_checksum():
    good = E.nodeframe4(1, 3, 10, 10, 4400, [(2, 88, [(0, 1000), (1, 2000)])])
    assert decode_frame(good).type == "NodeFrame4"
    b = bytearray(good)
    b[25] = 3  # anchor_count 2 -> 3: the walk overruns; fix the checksum so only the walk can catch it
    bad = E.with_checksum(bytes(b[:-1]))
    with pytest.raises(FrameError):
        decode_frame(bad)
    frames, stats = decode(bad)
    assert frames == [] and stats.checksum_failures == 1


def test_unknown_frame_kept_raw_and_false_unknown_vetoed():
    unk = E.unknown_frame(0x21, b"\x01\x02\x03")
    frames, _ = decode(unk)
    assert frames[0].type == "unknown" and frames[0].raw == unk and frames[0].fields["mark"] == 0x21
    # a "frame" with an unknown mark that checks out but contains a real NodeFrame3 is not accepted
    nf3 = E.nodeframe3(0, 1, 5, 5, 4000, [(0, 2, 1234, 180, 170)])
    for filler in range(256):
        body = bytes([0x55, 0x30]) + (4 + 1 + len(nf3) + 1).to_bytes(2, "little") + bytes([filler]) + nf3
        fake = E.with_checksum(body)
        frames, _ = decode(fake + b"\x00" * 8)
        assert [f.raw for f in frames] == [nf3]


def test_node_ids_carry_the_role():
    assert nlink.node_id(1, 3) == "A3" and nlink.node_id(2, 3) == "T3" and nlink.node_id(0, 7) == "N7"
    assert nlink.node_id(9, 1) == "R9_1"


# ---------------------------------------------------------------------------------------- properties

_segments = st.lists(
    st.one_of(st.binary(max_size=60), st.integers(0, 2**31).map(lambda s: E.random_nlink_frame(random.Random(s)))),
    max_size=12,
)


@settings(max_examples=150, deadline=None)
@given(_segments, st.lists(st.integers(1, 400), max_size=30))
def test_chunking_does_not_change_the_result(segments, cuts):
    data = b"".join(segments)
    whole, ws = decode(data)
    d = NLinkDecoder()
    out, i = [], 0
    for c in cuts:
        out += d.feed(data[i : i + c])
        i += c
    out += d.feed(data[i:]) + d.finish()
    assert [f.raw for f in out] == [f.raw for f in whole]
    assert d.stats == ws
    # every byte is accounted for: in a frame or skipped
    assert ws.bytes_fed == len(data) == sum(len(f.raw) for f in whole) + ws.bytes_skipped


@settings(max_examples=150, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 2**31), st.binary(max_size=40).map(lambda b: b.replace(b"\x55", b""))), max_size=10
    ),
    st.integers(0, 2**31),
)
def test_valid_frames_between_garbage_are_all_recovered(items, seed):
    frames = [E.random_nlink_frame(random.Random(s)) for s, _ in items]
    data = b"".join(g + f for (_, g), f in zip(items, frames, strict=False))
    rng = random.Random(seed)
    d, out, i = NLinkDecoder(), [], 0
    while i < len(data):
        k = rng.randrange(1, 300)
        out += d.feed(data[i : i + k])
        i += k
    out += d.finish()
    assert [f.raw for f in out] == frames


_u8 = st.integers(0, 255)
_dis = st.integers(-(1 << 23), (1 << 23) - 1)


@settings(max_examples=100, deadline=None)
@given(
    _u8,
    _u8,
    st.integers(0, 2**32 - 1),
    st.integers(0, 2**32 - 1),
    st.integers(0, 65535),
    st.lists(st.tuples(_u8, _u8, _dis, _u8, _u8), max_size=20),
)
def test_nodeframe3_round_trip(role, ident, lt, syt, mv, nodes):
    f = decode_frame(E.nodeframe3(role, ident, lt, syt, mv, nodes))
    assert (f.fields["role"], f.fields["id"], f.fields["local_time"], f.fields["system_time"]) == (role, ident, lt, syt)
    assert f.fields["voltage"] == mv / 1000
    assert [(n["role"], n["id"], n["dis"], n["fp_rssi"], n["rx_rssi"]) for n in f.fields["nodes"]] == [
        (r, i, d / 1000, fp / -2, rx / -2) for r, i, d, fp, rx in nodes
    ]
    assert f.device_time_ms == lt


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(_u8, _u8, st.lists(st.tuples(_u8, _dis), max_size=8)), max_size=8))
def test_nodeframe4_round_trip(tags):
    f = decode_frame(E.nodeframe4(1, 2, 3, 4, 4000, tags))
    assert [(t["id"], t["voltage"], t["anchors"]) for t in f.fields["tags"]] == [
        (tid, tv / 20, {a: d / 1000 for a, d in anchors}) for tid, tv, anchors in tags
    ]
    assert len(f.ranges) == sum(len(anchors) for _, _, anchors in tags)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 254), st.integers(0, 6), st.lists(st.integers(0, 65535), min_size=8, max_size=8)),
        max_size=30,
    )
)
def test_anchorframe0_round_trip(slots):
    raw = E.anchorframe0([(i, r, (1, -2, 3), dis) for i, r, dis in slots], 7, 8, 4321)
    f = decode_frame(raw)
    assert [(n["id"], n["role"], n["dis"]) for n in f.fields["nodes"]] == [
        (i, r, tuple(d / 100 for d in dis)) for i, r, dis in slots
    ]
    assert len(f.ranges) == sum(sum(1 for d in dis if d) for _, _, dis in slots)


def test_long_hostile_stream_exact_recovery():
    """Random valid frames of every type, bit-flipped frames and garbage (0x55 included), random splits:
    each valid frame comes out exactly once, in order, and no corrupted one does."""
    rng = random.Random(2024)
    data, valid = E.hostile_stream(rng, 3000)
    d, out, i = NLinkDecoder(), [], 0
    while i < len(data):
        k = rng.randrange(1, 700)
        out += d.feed(data[i : i + k])
        i += k
    out += d.finish()
    assert [f.raw for f in out] == valid
    assert d.stats.checksum_failures > 0.1 * 3000
    assert d.stats.bytes_fed == sum(map(len, valid)) + d.stats.bytes_skipped
