"""`jaxcal evaluate RESULT.h5 --truth DATASET.h5 [--json]`: errors of a calibration against ground truth."""

from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("result", help="a result file (from `jaxcal calibrate`)")
    p.add_argument("--truth", required=True, help="the dataset with ground truth (mesh or trajectory)")
    from jaxcal.commands._common import add_output_flags

    add_output_flags(p)


def run(args) -> int:
    from jaxcal.commands._common import kind_of, load, print_json
    from jaxcal.metrics import evaluate

    result = load(args.result, ("result",))
    truth = load(args.truth, ("mesh", "trajectory"))
    report = evaluate(result, truth)
    none: list[str] = []
    if kind_of(truth) == "mesh":  # text only: the JSON report is the contract's, key for key (a node
        import numpy as np  # without an estimate has "final_error_m": null there)

        none = [result.ids[i] for i in np.flatnonzero(~np.isfinite(result.position).all(axis=1))]
    if args.json:
        report.pop("ecdf", None)
        print_json(report)
        return 0
    if args.quiet:
        return 0
    fmt = lambda v: "    -" if v is None or v != v else f"{v:7.3f}"  # noqa: E731
    print(f"{report['method']} on {report['dataset']}")
    if kind_of(truth) == "mesh":
        print(
            f"rmse {fmt(report['rmse_m'])} m   final rmse {fmt(report['final_rmse_m'])} m   "
            f"aligned rmse {fmt(report['aligned_rmse_m'])} m"
        )
        _print_consistency(result, truth, fmt)
        if none:
            print(
                f"{len(none)} of {len(report['nodes'])} nodes have no estimate ({', '.join(none)}): "
                "the errors above are over the estimates that exist"
            )
        print(f"{'node':<12}{'rmse [m]':>10}{'final [m]':>11}{'avail.':>8}")
        for n in report["nodes"]:
            print(f"{n['id']:<12}{fmt(n['rmse_m']):>10}{fmt(n['final_error_m']):>11}{100 * n['availability']:>7.1f}%")
    else:
        print(f"mean error {fmt(report['mean_error_m'])} m")
        _print_consistency(result, truth, fmt)
        for a in report["anchors"]:
            print(f"{a['id']:<12}{fmt(a['error_m']):>10}")
    return 0


def _print_consistency(result, truth, fmt) -> None:
    """Text only (the JSON report is the contract's, key for key): does the covariance hold the truth?"""
    from jaxcal.metrics import covariance_consistency

    cc = covariance_consistency(result, truth)
    if cc is None:
        return
    print(
        f"covariance: 95 % ellipses hold the truth for {100 * cc['coverage95']:.0f} % of {cc['nodes']}; "
        f"predicted rms {fmt(cc['predicted_rmse_m'])} m, actual {fmt(cc['error_rmse_m'])} m, "
        f"NEES per coordinate {cc['nees_per_dof']:.2f} (1 = calibrated, > 1 = overconfident)"
    )
    for part, label in (("h_", "horizontal"), ("v_", "vertical")):
        if f"{part}error_rmse_m" in cc:
            print(
                f"  {label:<10}: predicted rms {fmt(cc[part + 'predicted_rmse_m'])} m, "
                f"actual {fmt(cc[part + 'error_rmse_m'])} m, NEES per coordinate {cc[part + 'nees_per_dof']:.2f}, "
                f"95 % coverage {100 * cc[part + 'coverage95']:.0f} %"
            )
