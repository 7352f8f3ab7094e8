"""`jaxcal tune FILE --method pgp --objective truth|evidence -o PARAMS.json [--config NAME]
[--epochs K] [--cell M] [--set K=V ...]`: fit sigma_r, sigma_v and tau of the PGP filter by
gradient (Optimistix BFGS)."""

from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("dataset", help="a mesh file")
    p.add_argument("--method", default="pgp", choices=["pgp"], help="filter to tune (pgp)")
    p.add_argument(
        "--objective",
        default="truth",
        choices=["truth", "evidence"],
        help="truth: RMSE of the final positions (needs ground truth); evidence: negative log "
        "predictive likelihood of the ranges (no truth needed)",
    )
    p.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="PARAMS.json",
        help="parameters for `jaxcal calibrate --params`",
    )
    from jaxcal.commands._common import CONFIG_HELP, add_output_flags

    p.add_argument("--config", default=None, help=CONFIG_HELP)
    p.add_argument(
        "--epochs", type=int, default=200, help="tuning window: the first K epochs (200)"
    )
    p.add_argument("--cell", type=float, default=1.0, help="grid cell size while tuning [m] (1.0)")
    p.add_argument("--max-steps", type=int, default=30, help="BFGS step limit (30)")
    p.add_argument(
        "--tau-temp", type=float, default=0.05, help="temperature of the soft tau cut (0.05)"
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="fixed filter parameter (also the start of sigma_r, sigma_v, tau)",
    )
    add_output_flags(p, "print the outcome as one JSON object")


def run(args) -> int:
    import dataclasses
    import json

    import jax

    from jaxcal.commands._common import _clean, check_output_path, load, print_json, resolve_config
    from jaxcal.errors import JaxcalError
    from jaxcal.io.atomic import atomic_write_text
    from jaxcal.params import parse_set

    if args.epochs < 1 or not args.cell > 0 or args.max_steps < 1 or args.tau_temp < 0:
        raise JaxcalError("--epochs and --max-steps must be >= 1, --cell > 0, --tau-temp >= 0")
    out = check_output_path(args.output, [args.dataset])
    ds = load(args.dataset, ("mesh",))
    ds, config = resolve_config(ds, args.config)
    user = parse_set(args.set)
    if "cell_m" in user:
        raise JaxcalError("set the tuning grid with --cell, not --set cell_m")
    from jaxcal import tune as T

    with jax.enable_x64(True):  # gradients through 200 epochs of log posteriors need float64
        res = T.tune(
            ds,
            {**user, "cell_m": args.cell},
            config,
            objective_name=args.objective,
            epochs=args.epochs,
            tau_temp=args.tau_temp,
            max_steps=args.max_steps,
        )
    from jaxcal.mesh.pgp import PGPParams
    from jaxcal.params import with_overrides

    fixed = {k: getattr(with_overrides(PGPParams(), user), k) for k in user}
    doc = {
        "params": {**fixed, **res.params},
        "tuning": {
            "method": args.method,
            "dataset": ds.name,
            "config": args.config,
            **{f.name: getattr(res, f.name) for f in dataclasses.fields(res) if f.name != "params"},
        },
    }
    atomic_write_text(out.path, json.dumps(_clean(doc), indent=2))
    if args.json:
        print_json({**doc, "overwrote": out.existed})
    elif not args.quiet:
        p, hb, ha = res.params, res.hard_before, res.hard_after
        print(
            f"tune {args.objective}: {res.before:.4g} -> {res.after:.4g} in {res.steps} steps "
            f"({res.message}); sigma_r={p['sigma_r']:.3f} m sigma_v={p['sigma_v']:.3f} m "
            f"tau={p['tau']:.3f}"
            + (f" nlos_weight={p['nlos_weight']:.3f} nlos_mean_m={p['nlos_mean_m']:.3f} m"
               if "nlos_weight" in p else "")
            + "; "
            f"window rmse {hb['rmse_m']:.3f} -> {ha['rmse_m']:.3f} m, nlpl {hb['nlpl']:.3f} -> "
            f"{ha['nlpl']:.3f} -> {out}{out.note()}"
        )
    return 0
