"""`jaxcal tune FILE [FILE ...] --method pgp --objective evidence|consensus|truth|nlpl -o PARAMS.json [--config NAME]
[--tail K | --full] [--epochs K] [--cell M] [--max-steps S] [--set K=V ...]`: fit sigma_r, sigma_v
and tau of the PGP filter by gradient (Optimistix BFGS), keeping them only if `calibrate` does better
with them. Several files: one set of values for all of them (the mean objective; the guard pools them
and refuses when one recording gets clearly worse)."""

from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument(
        "dataset",
        nargs="+",
        help="a mesh file; several: tune one set of values on all of them (the mean of their "
        "objectives; the guard pools their held-out pairs or nodes and refuses if any one gets "
        "clearly worse), values that transfer better to recordings not tuned on",
    )
    p.add_argument("--method", default="pgp", choices=["pgp"], help="filter to tune (pgp)")
    p.add_argument(
        "--objective",
        default="evidence",
        choices=["evidence", "consensus", "truth", "nlpl"],
        help="evidence (default, no truth needed): predict the ranges of pairs held out from the "
        "filter (cross-validation over pairs); consensus (no truth needed): RMSE against the robust "
        "batch fit of the same recording (calibrate --method batch, estimate=map); truth: RMSE "
        "against the ground truth; nlpl: the filter's own predictive likelihood of the ranges (ranks "
        "parameters poorly)",
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
        "--epochs",
        type=int,
        default=200,
        help="gradient phase on the first K epochs (200; --full or --tail: all of them); the guard "
        "always checks calibrate's run on the whole recording",
    )
    p.add_argument(
        "--cell",
        type=float,
        default=None,
        help="grid cell of the gradient phase [m] (default: calibrate's cell_m, at least 1.0; "
        "--full or --tail: calibrate's)",
    )
    p.add_argument(
        "--full",
        action="store_true",
        help="gradient phase on exactly what calibrate runs (all epochs, its cell), differentiated "
        "through every epoch: ~6.5x a filter run per fold and step",
    )
    p.add_argument(
        "--tail",
        type=int,
        default=None,
        metavar="K",
        help="run calibrate's filter over the whole recording at its cell size, differentiated "
        "through the last K epochs only (the earlier ones are calibrate's run with the start "
        "values): steps cost ~K windowed epochs; the objective then sees the final estimates only",
    )
    p.add_argument("--max-steps", type=int, default=12, help="BFGS step limit (12)")
    p.add_argument("--tau-temp", type=float, default=0.05, help="temperature of the soft tau cut (0.05)")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="calibrate's filter parameter (fixed; the start of sigma_r, sigma_v, tau)",
    )
    add_output_flags(p, "print the outcome as one JSON object")


def _summary(res, objective: str, out) -> str:
    """One line: start and end values, and the guard's hard figure before and after."""

    def fmt(d):
        s = f"sigma_r={d['sigma_r']:.3f} m sigma_v={d['sigma_v']:.3f} m tau={d['tau']:.3f}"
        if "nlos_weight" in d:
            s += f" nlos_weight={d['nlos_weight']:.3f} nlos_mean_m={d['nlos_mean_m']:.3f} m"
        return s

    k = res.hard_key
    unit = " m" if k in ("rmse_m", "heldout_m", "consensus_m") else " nats/range"
    hb, ha = res.hard_before[k], res.hard_after[k]
    st = res.settings
    grad = st["epochs"] - st.get("grad_from", 0)
    on = (
        f"gradient through the last {grad} of {st['epochs']} epochs"
        if grad < st["epochs"]
        else f"gradient on {st['epochs']} epochs"
    )
    if st["epochs"] < st["check_epochs"]:
        on += f" (the first {st['epochs']} of {st['check_epochs']})"
    on += (
        f" at {st['cell_m']:g} m cells, guard on calibrate's run ({st['check_epochs']} epochs, "
        f"{st['check_cell_m']:g} m)"
    )
    used = st.get("objective_used", objective)
    name = objective
    if st.get("fallback_reason"):  # consensus without a batch fit: the held-out objective
        name += f" ({st['fallback_reason']}: {used})"
    elif used != objective:
        name += f" (fewer than 5 nodes, no pair to hold out: {used})"
    recs = st.get("recordings") or []
    if len(recs) > 1:  # a set: the figures are the recordings' means
        name += f" on {len(recs)} recordings (mean)"
        on = on.replace(" epochs", " epochs in all", 1)
    head = f"tune {name}: {res.steps} steps ({res.message}; {on}); start {fmt(res.start)}"
    if st.get("consensus_unplaced", -1) > 0:
        head += f" (the batch fit left {st['consensus_unplaced']} nodes unplaced: not scored)"
    t = st.get("guard_gain_t", float("nan"))
    if res.accepted:
        why = f"better by t = {t:.2f} > {st.get('guard_t_min', 1.0):g}" if t == t else "better"
        return (
            f"{head}; tuned {fmt(res.tuned)}; calibrate's {k} {hb:.4g} -> {ha:.4g}{unit}"
            f" ({why}: tuned values written) -> {out}"
        )
    if res.tuned == res.start:
        return f"{head}; the optimiser did not move: calibrate's {k} {hb:.4g}{unit}; kept the start values -> {out}"
    units = {"heldout_m": "held-out pairs'", "consensus_m": "nodes'"}
    if st.get("worse_recording"):  # better over the set, but one recording clearly worse on its own
        own = {r["dataset"]: r["guard_gain_t"] for r in recs}[st["worse_recording"]]
        return (
            f"{head}; tuned {fmt(res.tuned)}: calibrate's {k} (mean) {hb:.4g} -> {ha:.4g}{unit} (t = {t:.2f}), "
            f"but {st['worse_recording']} got clearly worse (its own t = {own:.2f} < -{st.get('guard_t_min', 1.0):g}):"
            f" kept the start values -> {out}"
        )
    if k in units and ha < hb and t == t:  # better on average, but within the pairs' / nodes' scatter
        return (
            f"{head}; tuned {fmt(res.tuned)}: calibrate's {k} {hb:.4g} -> {ha:.4g}{unit} is within "
            f"the {units[k]} scatter (t = {t:.2f} <= {st.get('guard_t_min', 1.0):g}): kept the "
            f"start values -> {out}"
        )
    paired = f", t = {t:.2f}" if k in units and t == t else ""  # the guard's paired t, when it ran
    return (
        f"{head}; tuned {fmt(res.tuned)} not better under calibrate's {k} ({hb:.4g} -> "
        f"{ha:.4g}{unit}{paired}): kept the start values -> {out}"
    )


def run(args) -> int:
    import dataclasses
    import json
    import os
    import time

    from jaxcal.commands._common import check_output_path, load, print_json, resolve_config
    from jaxcal.errors import JaxcalError
    from jaxcal.io.atomic import atomic_write_text
    from jaxcal.io.jsonsafe import json_safe
    from jaxcal.params import parse_set
    from jaxcal.progress import progress_bar

    if (
        (args.epochs is not None and args.epochs < 1)
        or (args.cell is not None and not args.cell > 0)
        or (args.tail is not None and args.tail < 1)
        or args.max_steps < 1
        or args.tau_temp < 0
    ):
        raise JaxcalError("--epochs, --tail and --max-steps must be >= 1, --cell > 0, --tau-temp >= 0")
    out = check_output_path(args.output, args.dataset)
    if len(set(map(os.path.realpath, args.dataset))) < len(args.dataset):
        raise JaxcalError("tune: a file is given twice (each recording counts once in the mean)")
    sets = []
    for path in args.dataset:  # every file read and checked before the long work (the same name each)
        ds, config = resolve_config(load(path, ("mesh",)), args.config)
        sets.append(ds)
    if len({d.name for d in sets}) < len(sets):  # e.g. recordings of one site: name them by their files
        sets = [dataclasses.replace(d, name=path) for d, path in zip(sets, args.dataset, strict=True)]
    ds = sets[0]
    user = parse_set(args.set)
    epochs, cell = args.epochs, args.cell
    if args.full or args.tail:
        epochs = None
    elif cell is None:  # a cheaper surrogate for the gradient; the guard checks calibrate's own run
        from jaxcal.mesh.pgp import PGPParams
        from jaxcal.params import with_overrides

        cell = max(1.0, float(with_overrides(PGPParams(), user).cell_m))
    from jaxcal import tune as T

    t0 = time.perf_counter()
    with progress_bar(args.max_steps, "tune", "step", enabled=not (args.quiet or args.json)) as bar:
        mean = f" (mean of {len(sets)} recordings)" if len(sets) > 1 else ""

        def on_step(k, v):
            bar.set_postfix_str(f"objective{mean} {v:.4g}")

        res = T.tune(
            sets if len(sets) > 1 else ds,
            user,
            config,
            objective_name=args.objective,
            epochs=epochs,
            cell_m=cell,
            tail=None if args.full else args.tail,
            tau_temp=args.tau_temp,
            max_steps=args.max_steps,
            progress=bar.update,
            on_step=on_step,
            on_phase=bar.set_postfix_str,
        )
    from jaxcal.mesh.pgp import PGPParams
    from jaxcal.params import with_overrides

    fixed = {k: getattr(with_overrides(PGPParams(), user), k) for k in user}
    doc = {
        "params": {**fixed, **res.params},
        "tuning": {
            "method": args.method,
            "dataset": ds.name if len(sets) == 1 else [d.name for d in sets],
            "config": args.config,
            **{f.name: getattr(res, f.name) for f in dataclasses.fields(res) if f.name != "params"},
            "elapsed_s": time.perf_counter() - t0,
        },
    }
    atomic_write_text(out.path, json.dumps(json_safe(doc), indent=2))
    if args.json:
        print_json({**doc, "overwrote": out.existed})
    elif not args.quiet:
        print(_summary(res, args.objective, out.path) + out.note())
    return 0
