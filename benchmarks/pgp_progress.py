"""Benchmark: the cost of progress reporting in `run_pgp` (what `jaxcal calibrate` shows as a bar).

With a `progress` callback the fast path (`likelihood="window"`, default) reports after each of
its host chunks (no other change), and the one-scan paths (`likelihood="direct"`/"dense") run
their scan in segments of 64 epochs (`pgp.run_segmented`). Per likelihood: best of `--repeats`
warm `run_pgp` calls without and with a callback (compiled first, alternated), their ratio, and
whether the tracks and posteriors are bit-for-bit equal. One JSON line per likelihood.

Data: `data/torgau.h5` (else `simulate("torgau", 0)`), first `--epochs` epochs, conf1, float32.

Usage: python benchmarks/pgp_progress.py [--epochs 2000] [--cell 0.5] [--direct-epochs 200]
       [--direct-cell 1.0] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=2000)
    ap.add_argument("--cell", type=float, default=0.5)
    ap.add_argument("--direct-epochs", type=int, default=200)
    ap.add_argument("--direct-cell", type=float, default=1.0)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()

    import numpy as np

    from jaxcal.mesh.pgp import run_pgp
    from jaxcal.sim.mesh import simulate
    from jaxcal.tune import window

    path = ROOT / "data" / "torgau.h5"
    if path.exists():
        from jaxcal.io import hdf5

        full = hdf5.read(path)
    else:
        full = simulate("torgau", 0)
    for lik, epochs, cell in (
        ("window", a.epochs, a.cell),
        ("direct", a.direct_epochs, a.direct_cell),
    ):
        ds = window(full, epochs)
        p = {"cell_m": cell, "likelihood": lik}
        ticks = []
        plain = run_pgp(ds, p, "conf1")  # compile
        withp = run_pgp(ds, p, "conf1", progress=ticks.append)
        t_plain, t_prog = [], []
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            run_pgp(ds, p, "conf1")
            t_plain.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            run_pgp(ds, p, "conf1", progress=lambda n: None)
            t_prog.append(time.perf_counter() - t0)
        equal = np.array_equal(plain[0].track_position, withp[0].track_position, equal_nan=True) and np.array_equal(
            plain[1].posterior, withp[1].posterior
        )
        print(
            json.dumps(
                {
                    "bench": "pgp_progress",
                    "likelihood": lik,
                    "epochs": ds.n_epochs,
                    "cell_m": cell,
                    "callbacks": len(ticks),
                    "epochs_reported": int(sum(ticks)),
                    "plain_s": round(min(t_plain), 3),
                    "progress_s": round(min(t_prog), 3),
                    "ratio": round(min(t_prog) / min(t_plain), 3),
                    "bit_equal": bool(equal),
                    "loadavg": [round(x, 2) for x in os.getloadavg()],
                    "cpus": os.cpu_count(),
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
