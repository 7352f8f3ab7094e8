"""pgp on node-local grids: aligned RMSE with and without the localisation rule, over seeds (issue #26).

For each seed: a random network at constant density (`jaxcal.sim.network`, 200 epochs), then
`run_pgp` (default parameters, `conf1`) with `localise_m=0` (the global grid's rule of localisation)
and with the default `localise_m`. Prints one JSON line per seed: aligned RMSE, nodes placed, CPU
seconds (compilation included).

Usage:
    python benchmarks/pgp_local_seeds.py --nodes 40 --seeds 0,1,2,3,4
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
    a = ap.parse_args(argv)
    from jaxcal.mesh import pgp
    from jaxcal.sim.mesh import simulate
    from jaxcal.sim.network import network_scenario

    for seed in [int(s) for s in a.seeds.split(",") if s]:
        ds = simulate(network_scenario(a.nodes, seed=seed, n_epochs=a.epochs), seed=seed)
        truth = np.asarray(ds.truth)[:, :2]
        row = {"nodes": a.nodes, "seed": seed}
        for name, over in (("localise_m=0", {"localise_m": 0.0}), ("default", {})):
            c0 = time.process_time()
            res, _ = pgp.run_pgp(ds, over, "conf1", posterior=False)
            pos = np.asarray(res.position)
            row[name] = {
                "rmse_m": round(aligned_rmse(pos, truth), 4),
                "placed": int(np.isfinite(pos).all(axis=1).sum()),
                "cpu_s": round(time.process_time() - c0, 1),
            }
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
