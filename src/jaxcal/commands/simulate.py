"""`jaxcal simulate {mesh,trajectory} -o OUT.h5 [--scenario NAME] [--seed S] [--drift X]`."""

from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("kind", choices=("mesh", "trajectory"), help="what to simulate")
    p.add_argument(
        "-o", "--output", required=True, help="file to write (contract mesh / trajectory)"
    )
    p.add_argument(
        "--scenario",
        default=None,
        help="built-in scenario (mesh: torgau, small; trajectory: campus)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed, same file)")
    p.add_argument(
        "--drift",
        type=float,
        default=0.0,
        help="trajectory only: odometry drift (random walk) [m/sqrt(s)]",
    )
    from jaxcal.commands._common import add_output_flags

    add_output_flags(p, "print a JSON summary")


def _trajectory_simulator():
    from jaxcal.errors import JaxcalError

    try:
        from jaxcal.sim.trajectory import SCENARIOS, simulate
    except ModuleNotFoundError as e:
        if e.name != "jaxcal.sim.trajectory":
            raise
        raise JaxcalError(
            "trajectory simulation is not available yet (jaxcal.sim.trajectory missing)"
        ) from None
    return simulate, SCENARIOS


def run(args) -> int:
    from jaxcal.commands._common import check_output_path, emit_json, say
    from jaxcal.errors import JaxcalError
    from jaxcal.io import hdf5

    if args.kind == "mesh":
        from jaxcal.sim.mesh import SCENARIOS, simulate

        scenario = args.scenario or "torgau"
        if args.drift:
            raise JaxcalError("--drift applies to trajectory simulation only")
        kwargs = {}
    else:
        simulate, SCENARIOS = _trajectory_simulator()
        scenario = args.scenario or "campus"
        kwargs = {"drift": args.drift}
    if scenario not in SCENARIOS:
        raise JaxcalError(
            f"unknown {args.kind} scenario {scenario!r} (known: {', '.join(sorted(SCENARIOS))})"
        )
    if args.seed < 0:
        raise JaxcalError(f"--seed must be non-negative, got {args.seed}")
    out = check_output_path(args.output)
    ds = simulate(scenario, seed=args.seed, **kwargs)
    hdf5.write(out.path, ds)
    summary = {
        "kind": args.kind,
        "scenario": scenario,
        "seed": args.seed,
        "name": ds.name,
        "output": args.output,
        "overwrote": out.existed,
    }
    if args.kind == "mesh":
        summary.update(nodes=ds.n_nodes, epochs=ds.n_epochs)
    else:
        summary.update(anchors=ds.n_anchors, ranges=ds.n_ranges)
    emit_json(args, summary)
    size = (
        f"{summary['nodes']} nodes, {summary['epochs']} epochs"
        if args.kind == "mesh"
        else (f"{summary['anchors']} anchors, {summary['ranges']} ranges")
    )
    say(args, f"simulated {args.kind} scenario {scenario!r} (seed {args.seed}): {size} -> {args.output}{out.note()}")
    return 0
