"""Posterior sampler of `batch` (estimate=mean): two jaxcal source trees side by side on the real recordings.

Issue #22 asks for blackjax in place of the hand-written HMC of `batch.posterior_mean` (own leapfrog,
step-size rule, two-phase whitening). Branch `sampler-blackjax` has it (`jaxcal.mesh.sampler`: blackjax HMC
after its window adaptation); it was not merged (docs/benchmarks/index.md, "Batch sampler"). This script runs
`batch.solve(..., estimate=mean)` with the `jaxcal` on `sys.path` (point PYTHONPATH at a source tree) on
the three dwm1001-autocal scenarios (imported from ../shared/datasets, skipped when absent) and the
embedded `data/torgau.h5`, every frame configuration, and writes per run: the posterior mean and sd of
every node (the sampler's own covariance, before the pair-level widening), acceptance rate, split R-hat,
transitions per chain, and the wall / CPU time of a second (compiled) call.

Usage:
    PYTHONPATH=<old tree>/src python benchmarks/sampler_compare.py run --out old.json
    PYTHONPATH=<new tree>/src python benchmarks/sampler_compare.py run --out new.json
    python benchmarks/sampler_compare.py compare old.json new.json     # Markdown table
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `jaxcal` sets it for itself

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from uncertainty_real import datasets  # noqa: E402


def run(out: str, names: list[str], seed: int) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxcal.mesh import batch as B

    logging.getLogger("jaxcal").setLevel(logging.ERROR)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, ds in datasets(Path(tmp), names):
            t = np.asarray(ds.truth, dtype=float)
            dim = 3 if t.shape[1] == 3 and np.nanmax(t[:, 2]) - np.nanmin(t[:, 2]) > 0.5 else 2
            for cname, anchors in ds.configs:
                p = B.BatchParams(estimate="mean", dim=dim, seed=seed)
                B.solve(ds.range, anchors, p, ds.node_ids)  # compile
                t0, c0 = time.perf_counter(), time.process_time()
                sol = B.solve(ds.range, anchors, p, ds.node_ids)
                wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                cov = sol.model_covariance if sol.model_covariance is not None else sol.covariance
                sd = np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0.0, None))
                row = {
                    "dataset": name,
                    "config": cname,
                    "estimate": sol.estimate,
                    "mean": np.asarray(sol.position).tolist(),
                    "sd": sd.tolist(),
                    "accept": float(sol.mcmc_accept),
                    "rhat": float(sol.mcmc_rhat),
                    "transitions": int(sol.mcmc_transitions),
                    "seconds": round(wall, 2),
                    "cpu_s": round(cpu, 2),
                }
                print(json.dumps({k: v for k, v in row.items() if k not in ("mean", "sd")}), flush=True)
                rows.append(row)
    Path(out).write_text(json.dumps(rows))


def compare(old_path: str, new_path: str) -> None:
    old = {(r["dataset"], r["config"]): r for r in json.loads(Path(old_path).read_text())}
    new = {(r["dataset"], r["config"]): r for r in json.loads(Path(new_path).read_text())}
    print(
        "| dataset | config | max abs mean difference / sd | sd new / old (median, range) | R-hat old / new "
        "| acceptance old / new | transitions old / new | CPU s old / new |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for key in sorted(old.keys() & new.keys()):
        a, b = old[key], new[key]
        ma, mb = np.asarray(a["mean"], float), np.asarray(b["mean"], float)
        sa, sb = np.asarray(a["sd"], float), np.asarray(b["sd"], float)
        ok = (sa > 1e-9) & (sb > 1e-9) & np.isfinite(ma) & np.isfinite(mb)
        z = np.abs(ma - mb)[ok] / np.sqrt(0.5 * (sa**2 + sb**2))[ok]
        ratio = (sb / np.where(sa > 1e-9, sa, np.nan))[ok]
        print(
            f"| {key[0]} | {key[1]} | {z.max():.3f} | {np.median(ratio):.3f} ({ratio.min():.2f}-{ratio.max():.2f}) "
            f"| {a['rhat']:.4f} / {b['rhat']:.4f} | {a['accept']:.2f} / {b['accept']:.2f} "
            f"| {a['transitions']} / {b['transitions']} | {a['cpu_s']:.1f} / {b['cpu_s']:.1f} |"
        )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--out", required=True)
    r.add_argument("--datasets", default="campus_sport,srvlab_ground,3D_distribution,torgau")
    r.add_argument("--seed", type=int, default=0)
    c = sub.add_parser("compare")
    c.add_argument("old")
    c.add_argument("new")
    args = ap.parse_args(argv)
    if args.cmd == "run":
        run(args.out, args.datasets.split(","), args.seed)
    else:
        compare(args.old, args.new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
