"""`jaxcal calibrate DATASET.h5 --method M -o RESULT.h5 [--config NAME] [--set K=V ...] [--params P.json]`."""

from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("dataset", help="a mesh or trajectory file")
    p.add_argument("--method", required=True, help="mesh: cf, pgp, ...; trajectory: gp, nls, ls, ...")
    p.add_argument("-o", "--output", required=True, help="result file to write")
    p.add_argument("--config", default=None, help="mesh frame configuration (configs/<NAME>); default (0, 1, 2)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a method parameter")
    p.add_argument("--params", default=None, metavar="PARAMS.json", help="parameters from a JSON file (e.g. from `jaxcal tune`)")
    p.add_argument("--json", action="store_true", help="print a JSON summary of the result")


def run(args) -> int:
    import time

    from jaxcal.commands._common import load, print_json
    from jaxcal.io import hdf5
    from jaxcal.methods import calibrate
    from jaxcal.params import load_params_json, parse_set

    ds = load(args.dataset, ("mesh", "trajectory"))
    params = load_params_json(args.params) if args.params else {}
    params.update(parse_set(args.set))
    t0 = time.perf_counter()
    result = calibrate(ds, args.method, params=params, config=args.config)
    elapsed = time.perf_counter() - t0
    hdf5.write(args.output, result)
    import numpy as np

    from jaxcal.metrics import predicted_uncertainty

    n_est = int(np.isfinite(result.position).all(axis=1).sum())
    pu = predicted_uncertainty(result)
    pred = pu["predicted_rmse_m"]
    if args.json:
        print_json({"method": result.method, "dataset": result.dataset, "output": args.output,
                    "estimated": n_est, "nodes": len(result.ids), "seconds": elapsed,
                    "partial": pu["partial"], "predicted_rmse_m": pred if np.isfinite(pred) else None})
    else:
        partial = f" ({pu['partial']} with a coordinate not fixed)" if pu["partial"] else ""
        quality = f", predicted RMS uncertainty {pred:.3g} m" if np.isfinite(pred) else ", no covariance"
        print(f"{args.method}: {n_est}/{len(result.ids)} positions estimated{partial}{quality} in {elapsed:.2f} s "
              f"-> {args.output}")
    return 0
