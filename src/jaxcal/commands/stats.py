"""`jaxcal stats DATASET.h5 [--json]`: ranging error statistics by LOS / NLOS / all (Table I)."""

from __future__ import annotations

_ROWS = (
    ("mean_m", "Mean (m)"),
    ("median_m", "Median (m)"),
    ("variance_m2", "Variance (m^2)"),
    ("q1sigma_m", "1 sigma quantile (m)"),
    ("q2sigma_m", "2 sigma quantile (m)"),
    ("q3sigma_m", "3 sigma quantile (m)"),
    ("p25_m", "25th percentile (m)"),
    ("p50_m", "50th percentile (m)"),
    ("p75_m", "75th percentile (m)"),
)


def add_arguments(p) -> None:
    p.add_argument("dataset", help="a mesh or trajectory file with ground truth")
    from jaxcal.commands._common import add_output_flags

    add_output_flags(p, "print one JSON object instead of a table")


def format_table(groups: dict, reference: dict | None = None) -> str:
    """Table I as text: one column per group (share and count in the header); `reference` adds columns."""

    def head(g, label):
        share = groups[g]["share"]
        return f"{label} ({100 * share:.1f} %)" if share == share else f"{label} (-)"

    cols = [
        ("los", head("los", "LOS")),
        ("nlos", head("nlos", "NLOS")),
        ("all", head("all", "All")),
    ]
    lines = []
    header = f"{'':<22}" + "".join(f"{c[1]:>16}" for c in cols)
    if reference:
        header += "".join(f"{'paper ' + g.upper():>13}" for g in ("los", "nlos", "all"))
    lines.append(header)
    lines.append(f"{'count':<22}" + "".join(f"{groups[g]['count']:>16d}" for g, _ in cols))
    for key, label in _ROWS:
        row = f"{label:<22}" + "".join(f"{groups[g][key]:>16.2f}" for g, _ in cols)
        if reference:
            row += "".join(f"{reference[g].get(key, float('nan')):>13.2f}" for g in ("los", "nlos", "all"))
        lines.append(row)
    return "\n".join(lines)


def run(args) -> int:
    from jaxcal.commands._common import load, print_json
    from jaxcal.metrics import ranging_statistics

    ds = load(args.dataset, ("mesh", "trajectory"))
    groups = ranging_statistics(ds)
    if args.json:
        print_json({"groups": groups})
    elif not args.quiet:
        print(f"ranging errors |range - true distance| of {ds.name}")
        print(format_table(groups))
    return 0
