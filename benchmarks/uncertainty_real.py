"""Do the mesh methods' covariances hold the truth on the real recordings? Coverage and NEES per dataset.

Datasets: the three dwm1001-autocal scenarios (real DWM1001 meshes; imported at run time from
../shared/datasets with `jaxcal import dwm1001-autocal`, skipped when absent: they are not distributed
with jaxcal) and the embedded simulated `data/torgau.h5`. Every configuration (frame) of every dataset,
planar (dim 2) where the truth is planar, else 3-D for batch.

Printed (JSON lines): per (dataset, configuration, method) `metrics.covariance_consistency` (coverage at 95 %,
NEES per dof, predicted against actual RMS) and the count of confidently wrong nodes (finite covariance,
truth outside its 95 % ellipse).

Usage:
    python benchmarks/uncertainty_real.py [--methods batch,batch:estimate=map,pgp] [--datasets campus,torgau]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from peers import SHARED, import_dwm  # noqa: E402

DWM = {  # name -> (scenario folder, nodes_cfg stem)
    "campus_sport": ("campus_sport/rich_samples", "campus_sport"),
    "srvlab_ground": ("srvlab_ground", "srvlab_ground"),
    "3D_distribution": ("3D_distribution", "3D_distribution"),
}


def datasets(tmp: Path, names: list[str]):
    from jaxcal.io import hdf5

    for name in names:
        if name == "torgau":
            yield name, hdf5.read(ROOT / "data" / "torgau.h5")
            continue
        folder, cfg = DWM[name]
        if not SHARED.exists():
            print(f"# {SHARED} not found: {name} skipped", file=sys.stderr)
            continue
        data = import_dwm(tmp, name, folder, cfg)
        if data is not None:
            yield name, data


def main(argv=None) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    from scipy.stats import chi2

    from jaxcal.methods import calibrate
    from jaxcal.metrics import covariance_consistency, truth_in_result_frame

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", default="batch,batch:estimate=map,pgp")
    ap.add_argument("--datasets", default="campus_sport,srvlab_ground,3D_distribution,torgau")
    args = ap.parse_args(argv)
    logging.getLogger("jaxcal").setLevel(logging.ERROR)
    with tempfile.TemporaryDirectory() as tmp:
        for name, ds in datasets(Path(tmp), args.datasets.split(",")):
            t = np.asarray(ds.truth, dtype=float)
            dim = 3 if t.shape[1] == 3 and np.nanmax(t[:, 2]) - np.nanmin(t[:, 2]) > 0.5 else 2
            for cname, _ in ds.configs:
                for m in args.methods.split(","):
                    meth, _, sets = m.partition(":")
                    params = dict(kv.split("=", 1) for kv in sets.split(",") if kv)
                    if meth.startswith("batch") and dim == 3:
                        params["dim"] = "3"
                    if meth in ("pgp", "parametric") and dim == 3:
                        continue  # the grid filter is planar
                    t0 = time.perf_counter()
                    try:
                        res = calibrate(ds, meth, params, cname)
                    except Exception as exc:  # noqa: BLE001 - one line per failed run, the rest go on
                        print(json.dumps({"dataset": name, "config": cname, "method": m, "error": str(exc)[:200]}))
                        continue
                    cc = covariance_consistency(res, ds) or {}
                    # confidently wrong: a finite covariance whose 95 % ellipse misses the truth
                    truth = truth_in_result_frame(res, t)
                    if truth.shape[1] == 3:
                        mirror = truth * np.array([1.0, 1.0, -1.0])
                        if np.nansum((res.position - mirror) ** 2) < np.nansum((res.position - truth) ** 2):
                            truth = mirror
                    wrong = 0
                    for k in range(len(res.ids)):
                        c, e = res.covariance[k], res.position[k] - truth[k]
                        if not (np.isfinite(c).all() and np.isfinite(e).all()):
                            continue
                        free = np.diag(c) > 1e-12
                        if free.any():
                            q = e[free] @ np.linalg.solve(c[np.ix_(free, free)], e[free])
                            wrong += int(q > chi2.ppf(0.95, int(free.sum())))
                    print(
                        json.dumps(
                            {
                                "dataset": name,
                                "config": cname,
                                "method": m,
                                "dim": dim,
                                "seconds": round(time.perf_counter() - t0, 1),
                                "confidently_wrong": wrong,
                                **{k: (round(v, 4) if isinstance(v, float) else v) for k, v in cc.items()},
                            }
                        ),
                        flush=True,
                    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
