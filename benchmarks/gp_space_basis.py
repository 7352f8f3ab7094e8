"""Issue #19: the spatial GP (`gp` with `model=space`) against its basis size, on real recordings and a
simulated family (JSON lines; `--table` prints the markdown table of the docs).

    python benchmarks/gp_space_basis.py [FILE.h5 ...] [--basis 12 16 20 28] [--seeds 10 --first-seed 1
        --seed-step 2 --scenario small --drift 0] > LOG
    python benchmarks/gp_space_basis.py --table LOG ...

Per dataset: `nls` once, then `gp model=space n_basis=N` per basis size: mean 3-D anchor error (a NaN
height counts with its horizontal error), the ratio to `nls`'s, process CPU seconds of the call (one cold
call: compilation included) and the 1-minute load average. On a shared CPU set
XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1".
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections import defaultdict

import numpy as np

from jaxcal.io import hdf5
from jaxcal.methods import calibrate


def mean_error(ds, est) -> float:
    e = np.asarray(est) - np.asarray(ds.anchor_truth)
    full = np.isfinite(e).all(axis=1)
    hor = np.isfinite(e[:, :2]).all(axis=1)
    err = np.where(full, np.linalg.norm(np.nan_to_num(e), axis=1), np.linalg.norm(np.nan_to_num(e[:, :2]), axis=1))
    return float(err[hor].mean()) if hor.any() else float("nan")


def run(ds, label, bases):
    c0 = time.process_time()
    ref = mean_error(ds, calibrate(ds, "nls", {}).position)
    line = {"dataset": label, "method": "nls", "mean_error_m": ref, "cpu_s": round(time.process_time() - c0, 2)}
    print(json.dumps({**line, "load1": round(os.getloadavg()[0], 2)}), flush=True)
    for nb in bases:
        c0 = time.process_time()
        res = calibrate(ds, "gp", {"model": "space", "n_basis": nb})
        err = mean_error(ds, res.position)
        out = {"dataset": label, "method": f"space n_basis={nb}", "mean_error_m": err, "ratio_nls": err / ref}
        out["fallback"] = int(np.sum(res.params.get("info_fallback_nls", [])))
        out["cpu_s"] = round(time.process_time() - c0, 2)
        print(json.dumps({**out, "load1": round(os.getloadavg()[0], 2)}), flush=True)


def table(paths):
    """Per dataset (a family: median and worst over its seeds) and basis size: error / nls, CPU s."""
    import re

    rows = defaultdict(list)
    for path in paths:
        for line in open(path):
            if line.startswith("{"):
                d = json.loads(line)
                if "ratio_nls" in d:
                    rows[(re.sub(r" seed=\d+", "", d["dataset"]), d["method"])].append(d)
    print("| dataset | method | runs | space / nls median | worst | mean error [m] median | CPU s median |")
    print("|---|---|---|---|---|---|---|")
    for (ds, m), v in rows.items():
        ratio = [d["ratio_nls"] for d in v]
        err = np.median([d["mean_error_m"] for d in v])
        cpu = np.median([d["cpu_s"] for d in v])
        print(f"| {ds} | {m} | {len(v)} | {np.median(ratio):.3f} | {np.max(ratio):.3f} | {err:.3f} | {cpu:.1f} |")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("files", nargs="*")
    ap.add_argument("--table", nargs="*", help="print the markdown table of these logs and exit")
    ap.add_argument("--basis", nargs="*", type=int, default=[12, 16, 20, 28])
    ap.add_argument("--seeds", type=int, default=0)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--seed-step", type=int, default=2, help="2: every other seed (a development or report half)")
    ap.add_argument("--scenario", default="small")
    ap.add_argument("--drift", type=float, default=0.0)
    a = ap.parse_args()
    if a.table:
        table(a.table)
        return
    for f in a.files:
        run(hdf5.read(f), os.path.basename(f), a.basis)
    if a.seeds:
        from jaxcal.sim.trajectory import simulate

        for seed in range(a.first_seed, a.first_seed + a.seeds * a.seed_step, a.seed_step):
            run(simulate(a.scenario, seed=seed, drift=a.drift), f"{a.scenario} drift={a.drift:g} seed={seed}", a.basis)


if __name__ == "__main__":
    main()
