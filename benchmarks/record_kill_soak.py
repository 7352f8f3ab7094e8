"""Soak `jaxcal record --port` under SIGKILL: many kills at random moments on pseudo-terminals, for NLink
(100 Hz), DWM1001 TLV (20 Hz polls answered by the simulated module) and the DWM1001 shell (`--init`,
20 Hz `lec` lines), as tests/test_record_pty.py does 20 times in the suite (same code: tests/ptydev.py).

Each kill: a fresh recorder process; the simulated module sends items until a random one, of which a
random part (possibly none) is written, waits a random fraction of a period, and SIGKILLs the recorder.
The journal is replayed and compared with the items the recorder had read completely (bytes written
minus those still unread in the pty). A kill passes when the journal is a prefix of the items sent and
holds all the completely read items but those of the read in flight (one item while the recorder keeps up;
on a starved machine a read can hold several, and the device measures the largest), and the --raw-out
capture is a prefix of the stream holding every byte read but at most the read in flight. One JSON line per kill,
then one summary line per protocol and one overall. Where the kill left an HDF5 snapshot, it must be a
complete contract file whose frames are a prefix of the journal.

    PYTHONPATH=src .venv/bin/python benchmarks/record_kill_soak.py [--kills 30] [--workers 4] [--seed0 1000]
        [--seconds 4]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from ptydev import kill_ok, kill_run  # noqa: E402

RATE = {"nlink": 100, "dwm1001-tlv": 20, "dwm1001-shell": 20}  # items per second (tests/ptydev.py)


def _one(tmp: Path, protocol: str, seed: int, n: int) -> dict:
    try:
        return kill_run(tmp, protocol, seed, n)
    except AssertionError as e:  # a broken snapshot or a run that never started: a failure, reported
        return {
            "protocol": protocol,
            "seed": seed,
            "sent": 0,
            "partial": False,
            "read_complete": 0,
            "recovered": 0,
            "prefix": False,
            "snapshot_at_kill": None,
            "snapshot_frames": None,
            "read_bytes": 0,
            "raw_bytes": 0,
            "max_item": 0,
            "max_read_items": 0,
            "max_read_bytes": 0,
            "error": str(e),
        }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=int, default=30, help="kills per protocol (default 30)")
    ap.add_argument("--workers", type=int, default=4, help="recorders killed in parallel (default 4)")
    ap.add_argument("--seed0", type=int, default=1000, help="first seed (kill moments are drawn per seed)")
    ap.add_argument("--protocols", default="nlink,dwm1001-tlv,dwm1001-shell")
    ap.add_argument(
        "--seconds",
        type=float,
        default=4.0,
        help="stream length; the kill falls uniformly in it (default 4 s; longer streams put more "
        "kills after the first HDF5 snapshot)",
    )
    a = ap.parse_args()
    items = {p: max(2, int(a.seconds * r)) for p, r in RATE.items()}
    jobs = [(p, a.seed0 + k) for p in a.protocols.split(",") for k in range(a.kills)]
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp, ThreadPoolExecutor(a.workers) as pool:
        runs = list(pool.map(lambda j: _one(Path(tmp), j[0], j[1], items[j[0]]), jobs))
    total = {
        "kills": 0,
        "sent": 0,
        "read": 0,
        "recovered": 0,
        "lost_being_decoded": 0,
        "failures": 0,
        "kills_after_first_snapshot": 0,
        "bytes_read": 0,
        "bytes_in_raw_capture": 0,
    }
    per: dict[str, dict] = {}
    for r in runs:
        ok = "error" not in r and kill_ok(r)
        row = {
            k: r.get(k)
            for k in (
                "protocol",
                "seed",
                "sent",
                "partial",
                "read_complete",
                "recovered",
                "snapshot_at_kill",
                "snapshot_frames",
                "read_bytes",
                "raw_bytes",
                "max_read_items",
            )
        }
        row["ok"] = bool(ok)
        if "error" in r:
            row["error"] = r["error"]
        print(json.dumps(row))
        for acc in (total, per.setdefault(r["protocol"], dict.fromkeys(total, 0))):
            acc["kills"] += 1
            acc["sent"] += r["sent"]
            acc["read"] += r["read_complete"]
            acc["recovered"] += r["recovered"]
            acc["lost_being_decoded"] += r["read_complete"] - r["recovered"]
            acc["failures"] += not ok
            acc["kills_after_first_snapshot"] += r["snapshot_frames"] is not None
            acc["bytes_read"] += r.get("read_bytes", 0)
            acc["bytes_in_raw_capture"] += r.get("raw_bytes", 0)
    for p, acc in per.items():
        print(json.dumps({"summary": p, **acc}))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    print(
        json.dumps(
            {
                "summary": "all",
                **total,
                "seconds": round(time.monotonic() - t0, 1),
                "workers": a.workers,
                "seconds_per_stream": a.seconds,
                "machine": platform.machine(),
                "cpus": os.cpu_count(),
                "load_1min": load,
            }
        )
    )
    return 1 if total["failures"] else 0


if __name__ == "__main__":
    raise SystemExit(main())
