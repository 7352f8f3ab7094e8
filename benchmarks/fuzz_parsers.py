"""Fuzz the serial decoders: feed at least a million random chunks (hostile streams of valid frames,
bit-flipped frames and garbage, cut at random points 1-63 bytes apart) to each incremental decoder;
count exceptions (must be zero) and measure throughput. Two runs per decoder: with one chunk in ten
replaced by pure random bytes (which breaks most frames), and without. One JSON line per run.

    .venv/bin/python benchmarks/fuzz_parsers.py [--chunks 1000000] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import platform
import random
import time

from jaxcal.io.serial import encode as E
from jaxcal.io.serial import make_decoder


def nlink_stream(rng: random.Random, n: int) -> tuple[bytes, int]:
    data, valid = E.hostile_stream(rng, n)
    return data, len(valid)


def tlv_stream(rng: random.Random, n: int) -> tuple[bytes, int]:
    out, valid = bytearray(), 0
    for _ in range(n):
        if rng.random() < 0.3:
            out += bytes(rng.randrange(256) for _ in range(rng.randrange(1, 40)))
        r = E.loc_get_tag(
            [rng.randrange(-9999, 9999) for _ in range(3)],
            50,
            [(rng.randrange(65536), rng.randrange(30000), 100, (1, 2, 3), 100) for _ in range(rng.randrange(1, 6))],
        )
        if rng.random() < 0.2:
            r = r[: rng.randrange(3, len(r))]  # truncated response
        else:
            valid += 1
        out += r
    return bytes(out), valid


def shell_stream(rng: random.Random, n: int) -> tuple[bytes, int]:
    out, valid = bytearray(), 0
    for _ in range(n):
        if rng.random() < 0.3:
            out += bytes(rng.randrange(256) for _ in range(rng.randrange(1, 40)))
        line = E.lec_line(
            [(f"{rng.randrange(65536):04X}", (1, 2, 3), rng.random() * 20) for _ in range(rng.randrange(1, 6))],
            (1.0, 2.0, 0.5),
            90,
        )
        if rng.random() < 0.2:
            b = bytearray(line)
            b[rng.randrange(len(b) - 2)] = rng.randrange(256)
            line = bytes(b)
        out += line
        valid += 1
    return bytes(out), valid


STREAMS = {"nlink": nlink_stream, "dwm1001-tlv": tlv_stream, "dwm1001-shell": shell_stream}


def fuzz(protocol: str, n_chunks: int, seed: int, noise_chunks: bool = True) -> dict:
    rng = random.Random(seed)
    base, _ = STREAMS[protocol](rng, 3000)
    noise = bytes(rng.randrange(256) for _ in range(1 << 16))
    sizes = [rng.randrange(1, 64) for _ in range(4096)]
    # pre-cut the chunks so that the timed loop is the decoder only
    chunks, pos, npos = [], 0, 0
    for i in range(n_chunks):
        k = sizes[i % 4096]
        if noise_chunks and i % 10 == 9:  # one chunk in ten is pure random bytes (breaks most frames)
            chunks.append(noise[npos : npos + k])
            npos = (npos + k) % (len(noise) - 64)
        else:
            if pos + k > len(base):
                pos = 0
            chunks.append(base[pos : pos + k])
            pos += k
    dec = make_decoder(protocol)
    exceptions, frames = 0, 0
    t0 = time.perf_counter()
    for c in chunks:
        try:
            frames += len(dec.feed(c))
        except Exception:  # noqa: BLE001 - counted: the requirement is zero
            exceptions += 1
            dec = make_decoder(protocol)
    frames += len(dec.finish())
    dt = time.perf_counter() - t0
    st = dec.stats
    nbytes = sum(map(len, chunks))
    return {
        "bench": "fuzz_parsers",
        "protocol": protocol,
        "noise_chunks": noise_chunks,
        "chunks": n_chunks,
        "bytes": nbytes,
        "frames": frames,
        "exceptions": exceptions,
        "checksum_failures": st.checksum_failures,
        "bytes_skipped": st.bytes_skipped,
        "seconds": round(dt, 3),
        "frames_per_s": round(frames / dt, 1),
        "chunks_per_s": round(n_chunks / dt, 1),
        "mbytes_per_s": round(nbytes / dt / 1e6, 3),
        "python": platform.python_version(),
        "machine": platform.machine(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--chunks", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--protocol", choices=tuple(STREAMS), action="append")
    args = ap.parse_args()
    for p in args.protocol or STREAMS:
        for noise in (True, False):
            print(json.dumps(fuzz(p, args.chunks, args.seed, noise)), flush=True)


if __name__ == "__main__":
    main()
