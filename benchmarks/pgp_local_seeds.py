"""pgp on large networks: aligned RMSE of parameter variants over seeds (issue #26).

For each seed: a random network at constant density (`jaxcal.sim.network`, 200 epochs), then
`run_pgp` (`conf1`) once per variant (a JSON object of name -> parameter overrides; by default
`localise_m=0`, the global grid's rule of localisation, against the defaults). Prints one JSON line per
seed: per variant aligned RMSE, nodes placed, CPU seconds (compilation included; the first variant
pays it), the fitted range offset (`bias`), then per variant the median and worst RMSE over the seeds.

Usage:
    python benchmarks/pgp_local_seeds.py --nodes 40 --seeds 0,1,2,3,4 \
        [--variants '{"bias=none": {"bias": "none"}, "default": {}}']
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from peers import aligned_rmse  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=40)
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--epochs", type=int, default=200)
    ap.add_argument("--variants", default='{"localise_m=0": {"localise_m": 0.0}, "default": {}}')
    a = ap.parse_args(argv)
    from jaxcal.mesh import pgp
    from jaxcal.sim.mesh import simulate
    from jaxcal.sim.network import network_scenario

    variants = json.loads(a.variants)
    rmse: dict[str, list[float]] = {name: [] for name in variants}
    for seed in [int(s) for s in a.seeds.split(",") if s]:
        ds = simulate(network_scenario(a.nodes, seed=seed, n_epochs=a.epochs), seed=seed)
        truth = np.asarray(ds.truth)[:, :2]
        row = {"nodes": a.nodes, "seed": seed}
        for name, over in variants.items():
            c0 = time.process_time()
            res, info = pgp.run_pgp(ds, over, "conf1", posterior=False)
            pos = np.asarray(res.position)
            row[name] = {
                "rmse_m": round(aligned_rmse(pos, truth), 4),
                "placed": int(np.isfinite(pos).all(axis=1).sum()),
                "cpu_s": round(time.process_time() - c0, 1),
                "offset_m": round(float(info.offset_m), 3),
            }
            rmse[name].append(row[name]["rmse_m"])
        print(json.dumps(row), flush=True)
    summary = {
        name: {"median_m": round(float(np.median(v)), 4), "worst_m": round(float(np.max(v)), 4)}
        for name, v in rmse.items()
    }
    print(json.dumps({"nodes": a.nodes, "summary": summary}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
