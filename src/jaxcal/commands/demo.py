"""`jaxcal demo [-o DIR]`: the paper's evaluation on the embedded simulated Torgau dataset.

Reads `data/torgau.h5` (written by `jaxcal.sim.mesh.simulate("torgau", seed=DEMO_SEED)` and shipped with
the repository; simulated afresh when missing), prints its ranging statistics next to Table I of the
paper, runs every registered mesh method among `DEMO_METHODS` for both configurations, evaluates each
against the truth, and prints RMSE and availability per node and configuration and the time per run.
Results go to DIR (default `./demo-out`) as contract result files plus `summary.json`.
"""

from __future__ import annotations

DEMO_METHODS = ("cf", "parametric", "pgp", "batch", "pgp+batch")
DEMO_SCENARIO = "torgau"
DEMO_SEED = 2024
DEMO_CONFIGS = ("conf1", "conf2")

# Table I of the grid paper (|range - true distance| statistics), for side-by-side printing.
PAPER_TABLE_I = {
    "los": {
        "share": 0.763,
        "mean_m": 0.28,
        "median_m": 0.21,
        "variance_m2": 1.59,
        "q1sigma_m": 0.26,
        "q2sigma_m": 0.47,
        "q3sigma_m": 0.73,
        "p25_m": 0.16,
        "p50_m": 0.21,
        "p75_m": 0.29,
    },
    "nlos": {
        "share": 0.237,
        "mean_m": 3.78,
        "median_m": 0.69,
        "variance_m2": 41.56,
        "q1sigma_m": 1.41,
        "q2sigma_m": 23.21,
        "q3sigma_m": 24.24,
        "p25_m": 0.54,
        "p50_m": 0.69,
        "p75_m": 3.79,
    },
    "all": {
        "share": 1.0,
        "mean_m": 1.11,
        "median_m": 0.25,
        "variance_m2": 13.26,
        "q1sigma_m": 0.35,
        "q2sigma_m": 5.07,
        "q3sigma_m": 23.63,
        "p25_m": 0.18,
        "p50_m": 0.25,
        "p75_m": 0.44,
    },
}


def add_arguments(p) -> None:
    p.add_argument("-o", "--output", default="demo-out", help="folder for the results (default ./demo-out)")
    p.add_argument(
        "--methods",
        default=None,
        help=f"comma-separated subset of {','.join(DEMO_METHODS)} (default: all registered)",
    )
    from jaxcal.commands._common import add_output_flags

    add_output_flags(p, "print the summary as one JSON object")


def embedded_dataset_path():
    """Path of the shipped default dataset `data/torgau.h5` (repository root, next to `src/`)."""
    from pathlib import Path

    import jaxcal

    return Path(jaxcal.__file__).resolve().parents[2] / "data" / f"{DEMO_SCENARIO}.h5"


def load_default_dataset():
    """The embedded dataset, or a fresh simulation with the same scenario and seed when it is missing."""
    from jaxcal.io import hdf5

    path = embedded_dataset_path()
    if path.is_file():
        return hdf5.read(path), str(path)
    from jaxcal.sim.mesh import simulate

    return simulate(DEMO_SCENARIO, seed=DEMO_SEED), f"simulated {DEMO_SCENARIO} seed {DEMO_SEED}"


def run(args) -> int:
    import sys
    import time
    from pathlib import Path

    from jaxcal.commands._common import check_output_path, print_json
    from jaxcal.commands.stats import format_table
    from jaxcal.errors import JaxcalError
    from jaxcal.io import hdf5
    from jaxcal.io.atomic import atomic_write_text
    from jaxcal.methods import MESH_METHODS, calibrate
    from jaxcal.metrics import evaluate, ranging_statistics

    out = Path(check_output_path(args.output, folder=True).path)
    methods = [m for m in DEMO_METHODS if m in MESH_METHODS]
    if args.methods:
        wanted = [m.strip() for m in args.methods.split(",") if m.strip()]
        unknown = [m for m in wanted if m not in MESH_METHODS]
        if unknown:
            raise JaxcalError(
                f"--methods: not registered: {', '.join(unknown)} (known: {', '.join(sorted(MESH_METHODS))})"
            )
        methods = wanted
    stream = sys.stderr if args.json else sys.stdout
    out.mkdir(parents=True, exist_ok=True)

    def say(*a):
        if not args.quiet:
            print(*a, file=stream, flush=True)  # flushed: the runs take a while, show progress

    ds, origin = load_default_dataset()
    groups = ranging_statistics(ds)
    say(f"dataset {ds.name}: {ds.n_nodes} nodes, {ds.n_epochs} epochs ({origin})")
    say("Ranging statistics |range - true distance| (simulated, then the paper's Table I):")
    say(format_table(groups, reference=PAPER_TABLE_I))

    summary: dict = {"dataset": ds.name, "source": origin, "groups": groups, "runs": []}
    results = []  # for the report
    for method in methods:
        for conf in DEMO_CONFIGS:
            t0 = time.perf_counter()
            try:
                result = calibrate(ds, method, config=conf)
            except Exception as e:  # one failing method must not hide the others' results
                summary["runs"].append({"method": method, "config": conf, "error": f"{type(e).__name__}: {e}"})
                say(f"{method} {conf}: failed ({type(e).__name__}: {' '.join(str(e).split())[:200]})")
                continue
            seconds = time.perf_counter() - t0
            say(f"{method} {conf}: {seconds:.1f} s")
            path = out / f"{ds.name}-{method.replace('+', '_')}-{conf}.h5"
            hdf5.write(path, result)
            results.append(result)
            report = evaluate(result, ds)
            report.pop("ecdf", None)
            summary["runs"].append(
                {
                    "method": method,
                    "config": conf,
                    "seconds": seconds,
                    "output": str(path),
                    **report,
                }
            )

    say("")
    say(_format_runs(summary["runs"], ds.node_ids))
    atomic_write_text(out / "summary.json", _json(summary))
    if results:
        from jaxcal.report import write_report

        say(f"report in {write_report(results, ds, out / 'report')}")
    if args.json:
        print_json(summary)
    elif not args.quiet:
        print(f"results in {out}/")
    return 0


def _json(obj) -> str:
    import json

    from jaxcal.io.jsonsafe import json_safe

    return json.dumps(json_safe(obj), indent=1, allow_nan=False)


def _format_runs(runs: list[dict], node_ids) -> str:
    """One block per method: per node RMSE over epochs [m], error of the final position [m] and
    availability [%] for each configuration."""

    def f(v, w=7, p=2):
        return f"{'-':>{w}}" if v is None or v != v else f"{v:{w}.{p}f}"

    lines = []
    by_method: dict[str, dict[str, dict]] = {}
    for r in runs:
        by_method.setdefault(r["method"], {})[r["config"]] = r
    for method, confs in by_method.items():
        lines.append(f"== {method} ==")
        head = f"{'node':<10}"
        for conf in DEMO_CONFIGS:
            head += f"{conf + ' rmse':>13}{'final':>8}{'avail':>8}"
        lines.append(head)
        for i, nid in enumerate(node_ids):
            row = f"{nid:<10}"
            for conf in DEMO_CONFIGS:
                rc = confs.get(conf)
                if rc is None or "error" in rc:
                    row += f"{'-':>13}{'-':>8}{'-':>8}"
                else:
                    n = rc["nodes"][i]
                    row += f"{f(n['rmse_m'], 13)}{f(n['final_error_m'], 8)}{f(100 * n['availability'], 7, 1)}%"
            lines.append(row)
        tot = f"{'all':<10}"
        tim = f"{'time [s]':<10}"
        for conf in DEMO_CONFIGS:
            rc = confs.get(conf)
            if rc is None or "error" in rc:
                tot += f"{'failed':>29}"
                tim += f"{'-':>29}"
            else:
                tot += f"{f(rc['rmse_m'], 13)}{f(rc['final_rmse_m'], 8)}{'':>8}"
                tim += f"{f(rc['seconds'], 13)}{'':>16}"
        lines += [tot, tim, ""]
    return "\n".join(lines)
