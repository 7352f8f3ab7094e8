"""`jaxcal simulate {mesh,trajectory} -o OUT.h5 [--scenario NAME] [--seed S] [--drift X]`.

Large mesh networks at constant density (`jaxcal.sim.network`):
`jaxcal simulate mesh --scenario network --nodes N [--density D] [--range-limit R] [--wall-density W]
[--epochs K] -o OUT.h5`.
"""

from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("kind", choices=("mesh", "trajectory"), help="what to simulate")
    p.add_argument("-o", "--output", required=True, help="file to write (contract mesh / trajectory)")
    p.add_argument(
        "--scenario",
        default=None,
        help="built-in scenario (mesh: torgau, small, network; trajectory: campus)",
    )
    net = p.add_argument_group("mesh --scenario network (random site at constant density)")
    net.add_argument("--nodes", type=int, default=None, help="number of nodes N (>= 4)")
    net.add_argument(
        "--density", type=float, default=100.0 / 60.0, help="nodes per 100 m^2 (default 1.67: 10 nodes in 30 x 20 m)"
    )
    net.add_argument(
        "--range-limit", type=float, default=28.0, help="pairs farther apart are never measured [m] (default 28)"
    )
    net.add_argument(
        "--wall-density",
        type=float,
        default=2.0 / 6.0,
        help="walls (4-12 m segments) per 100 m^2 (default 0.33: 2 per 600 m^2)",
    )
    net.add_argument("--epochs", type=int, default=200, help="epochs at 10 Hz (default 200)")
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
        raise JaxcalError("trajectory simulation is not available yet (jaxcal.sim.trajectory missing)") from None
    return simulate, SCENARIOS


def run(args) -> int:
    from jaxcal.commands._common import check_output_path, emit_json, say
    from jaxcal.data import MeshDataset
    from jaxcal.errors import JaxcalError
    from jaxcal.io import hdf5

    if args.seed < 0:
        raise JaxcalError(f"--seed must be non-negative, got {args.seed}")
    if args.kind != "mesh" and args.nodes is not None:
        raise JaxcalError("--nodes applies to mesh simulation only")
    network = args.kind == "mesh" and (args.scenario == "network" or args.nodes is not None)
    if network:
        from jaxcal.sim.mesh import simulate
        from jaxcal.sim.network import network_scenario

        if args.scenario not in (None, "network"):
            raise JaxcalError("--nodes applies to --scenario network only")
        if args.nodes is None:
            raise JaxcalError("--scenario network needs --nodes N")
        if args.drift:
            raise JaxcalError("--drift applies to trajectory simulation only")
        scenario = "network"
        kwargs: dict = {}
        SCENARIOS = {
            scenario: network_scenario(
                args.nodes,
                seed=args.seed,
                density=args.density,
                range_limit_m=args.range_limit,
                wall_density=args.wall_density,
                n_epochs=args.epochs,
            )
        }
    elif args.kind == "mesh":
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
        raise JaxcalError(f"unknown {args.kind} scenario {scenario!r} (known: {', '.join(sorted(SCENARIOS))})")
    out = check_output_path(args.output)
    ds = simulate(SCENARIOS[scenario] if network else scenario, seed=args.seed, **kwargs)
    hdf5.write(out.path, ds)
    summary = {
        "kind": args.kind,
        "scenario": scenario,
        "seed": args.seed,
        "name": ds.name,
        "output": args.output,
        "overwrote": out.existed,
    }
    if isinstance(ds, MeshDataset):
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
