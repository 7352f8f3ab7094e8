"""PGP with the paper's Gaussian range kernel against the NLOS-aware mixture kernel (eq. 11).

Runs `jaxcal.mesh.pgp.calibrate` with `range_model="gaussian"` and `"mixture"` (its default
`nlos_weight`, `nlos_mean_m`, or the grid given by `--weights` / `--means`), everything else at the
defaults, on the simulated `torgau` configurations (several seeds) and on the dwm1001-autocal
scenarios (imported at run time from ../shared/datasets, as `peers.py` does; skipped when absent).

Metrics per run: RMSE over node-epochs (a0 excluded), final-position RMSE, aligned RMSE, seconds.
Prints one JSON line per run and a table of mixture-minus-Gaussian differences at the end.

Usage:
    python benchmarks/nlos_likelihood.py [--seeds 0,1] [--epochs 2000] [--weights 0.2] [--means 1.0]
        [--skip-real] [--skip-sim]
"""

from __future__ import annotations

import argparse
import itertools
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv=None) -> int:
    from peers import import_real  # same import of the real files as the peers benchmark

    from jaxcal.mesh import pgp
    from jaxcal.metrics import evaluate_mesh
    from jaxcal.sim.mesh import simulate

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--epochs", type=int, default=2000, help="epochs of the simulated runs")
    ap.add_argument("--weights", default=str(pgp.PGPParams.nlos_weight))
    ap.add_argument("--means", default=str(pgp.PGPParams.nlos_mean_m))
    ap.add_argument("--skip-real", action="store_true")
    ap.add_argument("--skip-sim", action="store_true")
    args = ap.parse_args(argv)
    models = [("gaussian", {})] + [
        (f"mixture w={w} m={m}", {"range_model": "mixture", "nlos_weight": float(w), "nlos_mean_m": float(m)})
        for w, m in itertools.product(args.weights.split(","), args.means.split(","))
    ]
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        if not args.skip_sim:
            for seed in (int(s) for s in args.seeds.split(",")):
                ds = simulate("torgau", seed=seed, n_epochs=args.epochs)
                runs += [(f"torgau-s{seed}/{c}", ds, c) for c in ("conf1", "conf2")]
        if not args.skip_real:
            for name, ds in import_real(Path(tmp)):
                runs += [(f"{name}/{c}", ds, c) for c in dict(ds.configs)]
        table = {}
        for label, ds, conf in runs:
            for model, over in models:
                t0 = time.perf_counter()
                res = pgp.calibrate(ds, over, config=conf)
                ev = evaluate_mesh(res, ds)
                rec = {
                    "dataset": label,
                    "model": model,
                    "rmse_m": ev["rmse_m"],
                    "final_rmse_m": ev["final_rmse_m"],
                    "aligned_rmse_m": ev["aligned_rmse_m"],
                    "seconds": time.perf_counter() - t0,
                    "epochs": ds.n_epochs,
                    "device": jax.devices()[0].platform,
                    "host": platform.node(),
                }
                table.setdefault(label, {})[model] = rec
                print(json.dumps(rec), flush=True)
    print("\nRMSE over node-epochs / final / aligned [m]")
    for label, row in table.items():
        cells = "  ".join(
            f"{m}: {r['rmse_m']:.3f}/{r['final_rmse_m']:.3f}/{r['aligned_rmse_m']:.3f}" for m, r in row.items()
        )
        print(f"{label:36s} {cells}")
    return 0


if __name__ == "__main__":
    try:
        raise SystemExit(main())
    except ValueError as e:  # bad --weights / --means / --seeds: one line, no traceback
        raise SystemExit(f"nlos_likelihood: error: {e}") from None
