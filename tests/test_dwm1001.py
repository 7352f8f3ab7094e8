"""DWM1001 decoders: TLV responses and shell lines from SPEC section 2 (read from ../shared, never
copied), stream resync and chunking properties."""

from __future__ import annotations

import random
import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import shared_path
from jaxcal.io.serial import dwm1001 as D
from jaxcal.io.serial import encode as E


def spec_text() -> str:
    return shared_path("protocols", "SPEC.md").read_text()


def spec_block(title: str) -> str:
    text = spec_text()
    i = text.index(title)
    return re.search(r"```\n(.*?)```", text[i:], re.S).group(1)


def spec_hex(title: str) -> bytes:
    return bytes.fromhex(spec_block(title))


def spec_line(prefix: str) -> bytes:
    """The first line of SPEC.md (stripped, backticks removed) that starts with `prefix`."""
    for line in spec_text().splitlines():
        s = line.strip()
        m = re.search(r"`([^`]+)`", s)
        if m and m.group(1).startswith(prefix):
            s = m.group(1)
        if s.startswith(prefix):
            return s.encode()
    raise AssertionError(prefix)


LOC_TAG = "**(a) Real capture, tag node, 3 anchors.**"
ANCHOR_LIST = "**(b) Real capture, `dwm_anchor_list_get`"
LOC_ANCHOR = "**(c) SYNTHETIC anchor-node loc_get.**"


# ------------------------------------------------------------------------------------------- TLV


def test_loc_get_tag_capture():
    raw = spec_hex(LOC_TAG)
    assert len(raw) == 81
    f = D.decode_tlv_response(raw)
    assert f.type == "loc_get" and f.fields["err"] == 0
    assert f.fields["position"] == (1.438, 1.328, 0.768) and f.fields["qf"] == 22
    got = [(a["id"], a["dist"], a["qf"], a["position"], a["pos_qf"]) for a in f.fields["anchors"]]
    assert got == [
        ("8287", 0.306, 100, (1.4, 1.69, 1.0), 100),
        ("1328", 0.259, 100, (1.76, 1.05, 1.0), 100),
        ("C584", 0.606, 100, (1.14, 1.02, 1.0), 100),
    ]
    assert [(r.src, r.dst, r.range_m, r.src_role) for r in f.ranges] == [
        ("tag", "8287", 0.306, "tag"),
        ("tag", "1328", 0.259, "tag"),
        ("tag", "C584", 0.606, "tag"),
    ]
    assert D.decode_tlv_response(raw, self_id="T7").ranges[0].src == "T7"
    # the encoder reproduces the capture
    assert (
        E.loc_get_tag(
            (1438, 1328, 768),
            22,
            [
                (0x8287, 306, 100, (1400, 1690, 1000), 100),
                (0x1328, 259, 100, (1760, 1050, 1000), 100),
                (0xC584, 606, 100, (1140, 1020, 1000), 100),
            ],
        )
        == raw
    )


def test_anchor_list_capture():
    f = D.decode_tlv_response(spec_hex(ANCHOR_LIST))
    assert f.type == "anchor_list_get"
    got = [(a["id"], a["position"], a["rssi"], a["seat"]) for a in f.fields["anchor_list"]]
    assert got == [
        ("C584", (1.34, 2.01, 3.06), -78, 0),
        ("0C0C", (1.5, 2.5, 3.0), -78, 1),
        ("1328", (1.56, 1.23, 3.41), -77, 2),
        ("9A1C", (64.0, 50.0, 18.0), -127, 4),
    ]
    assert f.ranges == ()


def test_loc_get_anchor_synthetic():
    f = D.decode_tlv_response(spec_hex(LOC_ANCHOR))
    assert f.type == "loc_get_anchor"
    assert f.fields["position"] == (0.0, 5.0, 2.25) and f.fields["qf"] == 100
    (t,) = f.fields["tags"]
    assert (t["addr"], t["dist"], t["qf"]) == (0xDECA343036200653, 3.19, 100)
    assert f.ranges[0][:3] == ("anchor", "0653", 3.19) and f.ranges[0].dst_role == "tag"


def test_error_and_pos_get():
    f = D.decode_tlv_response(b"\x40\x01\x01")
    assert f.type == "error" and f.fields["err"] == 1
    pos = spec_hex(LOC_TAG)[:18]
    f = D.decode_tlv_response(pos)
    assert f.type == "pos_get" and f.fields["position"] == (1.438, 1.328, 0.768)


@pytest.mark.parametrize(
    "bad",
    [
        b"\x41\x01\x00",  # not a status item
        b"\x40\x01\x09",  # err out of range
        b"\x40\x01\x00\x41\x0c" + bytes(12),  # position must be 13 bytes
        b"\x40\x01\x00\x49\x15\x02" + bytes(20),  # 0x49 with cnt 2 needs 41 bytes
        b"\x40\x01\x00\x48\x0a\x01" + bytes(9),  # 0x48 element neither 13 nor 7 bytes
        b"\x40\x01\x01\x41",  # error response with trailing bytes
    ],
)
def test_bad_tlv_responses_raise(bad):
    with pytest.raises(D.FrameError):
        D.decode_tlv_response(bad)


def test_tlv_stream_resync():
    a = spec_hex(LOC_TAG)
    c = spec_hex(LOC_ANCHOR)
    broken = a[:3] + b"\x49\x3d\x02" + a[21:]  # length 61 with cnt 2: inconsistent
    stream = b"\x01\x02" + a + b"\x40\x01\x01" + broken + c + b"lec\r" + a[:18] + b"\x40\x01\x01" + a + a[:40]
    rng = random.Random(3)
    for _ in range(40):
        d, out, i = D.TLVDecoder(), [], 0
        while i < len(stream):
            k = rng.randrange(1, 30)
            out += d.feed(stream[i : i + k])
            i += k
        out += d.finish()
        assert [f.type for f in out] == ["loc_get", "error", "loc_get_anchor", "pos_get", "error", "loc_get"]
        assert out[0].raw == a and out[2].raw == c and out[-1].raw == a
        assert d.stats.checksum_failures >= 1


@settings(max_examples=150, deadline=None)
@given(
    st.lists(
        st.one_of(st.binary(max_size=30), st.integers(0, 2**31).map(lambda s: _random_tlv(random.Random(s)))),
        max_size=10,
    ),
    st.lists(st.integers(1, 100), max_size=20),
)
def test_tlv_chunking_does_not_change_the_result(segments, cuts):
    data = b"".join(segments)
    whole, ws = D.decode_tlv(data)
    d, out, i = D.TLVDecoder(), [], 0
    for c in cuts:
        out += d.feed(data[i : i + c])
        i += c
    out += d.feed(data[i:]) + d.finish()
    assert [f.raw for f in out] == [f.raw for f in whole]
    assert d.stats == ws
    assert ws.bytes_fed == sum(len(f.raw) for f in whole) + ws.bytes_skipped


def _random_tlv(rng) -> bytes:
    if rng.random() < 0.5:
        return E.loc_get_tag(
            [rng.randrange(-9999, 9999) for _ in range(3)],
            rng.randrange(101),
            [
                (
                    rng.randrange(65536),
                    rng.randrange(20000),
                    rng.randrange(101),
                    [rng.randrange(-9999, 9999) for _ in range(3)],
                    100,
                )
                for _ in range(rng.randrange(5))
            ],
        )
    return E.loc_get_anchor(
        [1, 2, 3], 50, [(rng.randrange(1 << 64), rng.randrange(20000), 90) for _ in range(rng.randrange(4))]
    )


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 65535), st.integers(0, 2**32 - 1), st.integers(0, 255)), max_size=12))
def test_loc_get_round_trip(anchors):
    raw = E.loc_get_tag((1, 2, 3), 4, [(a, d, q, (5, 6, 7), 8) for a, d, q in anchors])
    f = D.decode_tlv_response(raw)
    assert [(a["addr"], a["dist"], a["qf"]) for a in f.fields["anchors"]] == [(a, d / 1000, q) for a, d, q in anchors]


# ----------------------------------------------------------------------------------------- shell


def test_shell_lines_from_spec():
    lec = spec_line("DIST,4,AN0,1151")
    les = spec_line("1151[5.00,8.00,2.25]=6.48")
    lep = spec_line("POS,2.57,2.00,1.67,97")
    f = D.parse_shell_line(lec)
    assert f.type == "lec"
    assert [a["dist"] for a in f.fields["anchors"]] == [6.44, 6.50, 3.24, 3.19]
    assert [a["id"] for a in f.fields["anchors"]] == ["1151", "0CA8", "111C", "1150"]
    assert f.fields["anchors"][0]["position"] == (5.0, 8.0, 2.25)
    assert f.fields["position"] == (2.55, 2.01, 1.71) and f.fields["qf"] == 98
    assert [(r.src, r.dst, r.range_m) for r in f.ranges][0] == ("tag", "1151", 6.44)
    g = D.parse_shell_line(les)
    assert g.type == "les" and g.fields["le_us"] == 2576
    assert g.fields["position"] == (2.57, 1.98, 1.68) and g.fields["qf"] == 100
    assert [a["dist"] for a in g.fields["anchors"]] == [6.48, 6.51, 3.18, 3.16]
    h = D.parse_shell_line(lep)
    assert h.type == "lep" and h.fields == {"position": (2.57, 2.0, 1.67), "qf": 97}


def test_real_shell_lines_and_garbled_line():
    f = D.parse_shell_line(spec_line("DIST,4,AN0,022E"))
    assert [a["dist"] for a in f.fields["anchors"]] == [3.44, 5.68, 7.76, 8.73]
    assert f.fields["position"] == (6.95, 5.37, -1.97) and f.fields["qf"] == 52
    g = D.parse_shell_line(spec_line("022E[7.94,8.03,0.00]=3.38"))
    assert g.fields["le_us"] == 3082 and g.fields["position"] == (6.97, 5.17, -1.77)
    three = D.parse_shell_line(spec_line("DIST,3,AN0,2F2F"))
    assert [a["id"] for a in three.fields["anchors"]] == ["2F2F", "2ED0", "2BA2"]
    assert three.fields["position"] == (1.76, 1.59, 0.51) and three.fields["qf"] == 40
    cut = spec_line("DIST,3,AN0,2F2F").split(b",POS")[0]  # the no-POS variant of SPEC 2.5
    assert "position" not in D.parse_shell_line(cut).fields
    with pytest.raises(D.FrameError):
        D.parse_shell_line(spec_line("DIST,4,AN0,0090"))  # the garbled real line must be rejected


def test_shell_stream_prompt_echo_log_unknown_and_bad_lines():
    lec = spec_line("DIST,4,AN0,1151")
    stream = (
        b"dwm> lec\r\n"
        + b"dwm> "
        + lec
        + b"\r\n"
        + b"\r\n"
        + b"[000541.880 INF] ble\r\n"
        + spec_line("DIST,4,AN0,0090")
        + b"\r\n"
        + b"DIST,4;[AN0,C584,160,0,-1510]=[1176,100];\r\n"
        + b"\x40\x01\x01\r\n"
        + b"x" * 3000
        + b"\r\n"
        + b"lec"
        + lec
        + b"\r\n"
        + lec[:30]
    )
    frames, stats = D.decode_shell(stream)
    assert [f.type for f in frames] == ["lec", "log", "unknown", "lec"]
    assert frames[0].fields["anchors"][3]["dist"] == 3.19 and frames[3].raw == b"lec" + lec
    # garbled DIST line, binary bytes, over-long line, truncated last line (parsed at end of stream)
    assert stats.checksum_failures == 4
    assert stats.by_type["lec"] == 2


@settings(max_examples=150, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.binary(max_size=40),
            st.sampled_from(
                [
                    E.lec_line([("1151", (5, 8, 2.25), 6.44), ("0CA8", (0, 8, 2.25), 6.5)], (1, 2, 3), 50),
                    E.les_line([("1151", (5, 8, 2.25), 6.48)], 2576, (2.5, 2.0, 1.7), 100),
                    b"dwm> ",
                    b"\r\n",
                    b"x" * 1100,
                    b"[000001.000 INF] x\r\n",
                ]
            ),
        ),
        max_size=12,
    ),
    st.lists(st.integers(1, 300), max_size=20),
)
def test_shell_chunking_does_not_change_the_result(segments, cuts):
    data = b"".join(segments)
    whole, ws = D.decode_shell(data)
    d, out, i = D.ShellDecoder(), [], 0
    for c in cuts:
        out += d.feed(data[i : i + c])
        i += c
    out += d.feed(data[i:]) + d.finish()
    assert [(f.type, f.raw) for f in out] == [(f.type, f.raw) for f in whole]
    assert d.stats == ws


@settings(max_examples=100, deadline=None)
@given(
    st.lists(st.tuples(st.integers(0, 65535), st.integers(-99999, 99999), st.integers(0, 99999)), max_size=8),
    st.one_of(st.none(), st.tuples(st.integers(-9999, 9999), st.integers(-9999, 9999), st.integers(-9999, 9999))),
    st.integers(0, 100),
)
def test_lec_round_trip(anchors, pos, qf):
    line = E.lec_line(
        [(f"{a:04X}", (x / 100, 1.0, 2.0), d / 100) for a, x, d in anchors],
        None if pos is None else tuple(v / 100 for v in pos),
        qf,
    )
    frames, stats = D.decode_shell(line)
    (f,) = frames
    assert [(a["id"], a["position"][0], a["dist"]) for a in f.fields["anchors"]] == [
        (f"{a:04X}", x / 100, d / 100) for a, x, d in anchors
    ]
    if pos is not None:
        assert f.fields["position"] == tuple(v / 100 for v in pos) and f.fields["qf"] == qf
