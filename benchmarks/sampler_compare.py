"""Posterior sampler of `batch` (estimate=mean): samplers side by side over sampler seeds.

Issue #22 asked for blackjax in place of the hand-written HMC of `batch.posterior_mean`. This script runs
`batch.solve(..., estimate=mean)` with each sampler named in `--samplers` (values of `BatchParams.sampler`:
`hmc`, `nuts`; `default`: the tree's default, for a tree without that field), taking turns on every case and
seed (so they share the machine's load), on the embedded `data/torgau.h5`, the three dwm1001-autocal
scenarios (imported at run time from ../shared/datasets, read in place; skipped when absent), and
simulated networks (`jaxcal simulate mesh --scenario network`), every frame configuration, and writes per
run: the posterior mean and sd of every node (the sampler's own covariance, before the pair-level
widening), acceptance rate, split R-hat, transitions per chain, and the CPU / wall time of the first call
(compilation included, what one `jaxcal calibrate` pays for the sampler: the fit is compiled before) and
of compiled calls, one per sampler seed (`--seeds`), with the load average.

Usage:
    PYTHONPATH=src python benchmarks/sampler_compare.py run --out runs.json --samplers hmc,nuts
    python benchmarks/sampler_compare.py compare runs.json             # Markdown table, first sampler = reference
Two source trees (e.g. before and after a sampler change), one after the other:
    PYTHONPATH=<old>/src python benchmarks/sampler_compare.py run --out old.json --samplers default --label old
    PYTHONPATH=<new>/src python benchmarks/sampler_compare.py run --out new.json --samplers default --label new
    python benchmarks/sampler_compare.py compare old.json new.json
The table in docs/benchmarks/uncertainty.md ("Batch sampler on blackjax") was made at commit 5723820, where
both samplers were in the tree (`--samplers jaxcal,blackjax`: the hand-written HMC and this blackjax one).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `jaxcal` sets it for itself

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from uncertainty_real import datasets  # noqa: E402


def networks(tmp: Path, sizes: list[int], seeds: list[int]):
    """Simulated networks (`jaxcal simulate mesh --scenario network`), as (name, dataset)."""
    from jaxcal.io import hdf5

    for n in sizes:
        for seed in seeds:
            path = tmp / f"net{n}_{seed}.h5"
            cmd = [sys.executable, "-m", "jaxcal.cli", "simulate", "mesh", "--scenario", "network"]
            cmd += ["--nodes", str(n), "--seed", str(seed), "-o", str(path), "--quiet"]
            subprocess.run(cmd, check=True)
            yield f"net{n}_seed{seed}", hdf5.read(path)


def _one(B, ds, anchors, dim: int, sampler: str, seed: int, calls: int, label: str) -> dict:
    """`calls` solves (the last one timed; more than one: the first compiles) -> one row."""
    chosen = {} if sampler == "default" else {"sampler": sampler}
    p = B.BatchParams(estimate="mean", dim=dim, seed=seed, **chosen)
    for _ in range(calls):
        t0, c0 = time.perf_counter(), time.process_time()
        sol = B.solve(ds.range, anchors, p, ds.node_ids)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    cov = sol.model_covariance if sol.model_covariance is not None else sol.covariance
    sd = np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0.0, None))
    return {
        "sampler": label or sampler,
        "seed": seed,
        "estimate": sol.estimate,
        "mean": np.asarray(sol.position).tolist(),
        "sd": sd.tolist(),
        "accept": float(sol.mcmc_accept),
        "rhat": float(sol.mcmc_rhat),
        "transitions": int(sol.mcmc_transitions),
        "cpu_s": round(cpu, 2),
        "seconds": round(wall, 2),
        "load": round(os.getloadavg()[0], 1),
    }


def run(out: str, names, samplers, sizes, net_seeds, seeds, label: str = "") -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxcal.mesh import batch as B

    logging.getLogger("jaxcal").setLevel(logging.ERROR)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cases = [*datasets(Path(tmp), names), *networks(Path(tmp), sizes, net_seeds)]
        for name, ds in cases:
            t = np.asarray(ds.truth, dtype=float)
            dim = 3 if t.shape[1] == 3 and np.nanmax(t[:, 2]) - np.nanmin(t[:, 2]) > 0.5 else 2
            for cname, anchors in ds.configs:
                B.solve(ds.range, anchors, B.BatchParams(estimate="map", dim=dim), ds.node_ids)  # compiles the fit
                first = {}
                for sampler in samplers:  # the first call compiles the sampler: what one `jaxcal calibrate` pays
                    first[sampler] = _one(B, ds, anchors, dim, sampler, seeds[0], 1, label)["cpu_s"]
                for seed in seeds:  # the samplers take turns, so that they share the machine's load
                    for sampler in samplers:
                        row = {"dataset": name, "config": cname, **_one(B, ds, anchors, dim, sampler, seed, 1, label)}
                        row["first_cpu_s"] = first[sampler]
                        print(json.dumps({k: v for k, v in row.items() if k not in ("mean", "sd")}), flush=True)
                        rows.append(row)
                Path(out).write_text(json.dumps(rows))


def _z(a: dict, b: dict) -> tuple[float, np.ndarray]:
    """Largest |mean a - mean b| / sd over the node coordinates, and the sd ratios b / a."""
    ma, mb = np.asarray(a["mean"], float), np.asarray(b["mean"], float)
    sa, sb = np.asarray(a["sd"], float), np.asarray(b["sd"], float)
    ok = (sa > 1e-9) & (sb > 1e-9) & np.isfinite(ma) & np.isfinite(mb)
    return float(np.max(np.abs(ma - mb)[ok] / np.sqrt(0.5 * (sa**2 + sb**2))[ok])), (sb[ok] / sa[ok])


def compare(paths: list[str]) -> None:
    rows = [r for path in paths for r in json.loads(Path(path).read_text())]
    samplers = list(dict.fromkeys(r["sampler"] for r in rows))
    ref = samplers[0]
    by = {(r["dataset"], r["config"], r["sampler"], r["seed"]): r for r in rows}
    print(
        f"| dataset | config | sampler | seeds | max abs mean difference / sd: vs {ref}, same seed (median, worst) "
        f"| {ref} seed vs next seed (median, worst) | sd / {ref} (median of medians) | R-hat (median, worst) "
        "| fell back "
        "| transitions (median, most) | CPU s compiled (median) | CPU s first call | load |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for dataset, config in dict.fromkeys((r["dataset"], r["config"]) for r in rows):
        seeds = sorted({r["seed"] for r in rows if (r["dataset"], r["config"]) == (dataset, config)})
        refs = [by.get((dataset, config, ref, s)) for s in seeds]
        noise = [
            _z(a, b)[0]
            for a, b in zip(refs, refs[1:], strict=False)
            if a and b and a["estimate"] == b["estimate"] == "mean"
        ]
        for name in samplers:
            got = [by[(dataset, config, name, s)] for s in seeds if (dataset, config, name, s) in by]
            if not got:
                continue
            pairs = [(by.get((dataset, config, ref, g["seed"])), g) for g in got]
            both = [(a, b) for a, b in pairs if a and a["estimate"] == b["estimate"] == "mean"]
            zs = [_z(a, b) for a, b in both] if name != ref else []
            z_text = f"{np.median([z for z, _ in zs]):.3f}, {max(z for z, _ in zs):.3f}" if zs else ""
            sd_text = f"{np.median([np.median(r) for _, r in zs]):.3f}" if zs else ""
            noise_text = f"{np.median(noise):.3f}, {max(noise):.3f}" if noise and name == ref else ""
            rh = np.array([g["rhat"] for g in got])
            tr = np.array([g["transitions"] for g in got])
            print(
                f"| {dataset} | {config} | {name} | {len(got)} | {z_text} | {noise_text} | {sd_text} "
                f"| {np.median(rh):.4f}, {rh.max():.4f} | {sum(g['estimate'] != 'mean' for g in got)} "
                f"| {np.median(tr):.0f}, {tr.max()} | {np.median([g['cpu_s'] for g in got]):.2f} "
                f"| {got[0]['first_cpu_s']:.1f} | {np.median([g['load'] for g in got]):.1f} |"
            )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--out", required=True)
    r.add_argument("--datasets", default="torgau,campus_sport,srvlab_ground,3D_distribution")
    r.add_argument("--samplers", default="hmc,nuts")
    r.add_argument("--label", default="", help="name the rows' sampler so (one sampler; e.g. old / new tree)")
    r.add_argument("--nodes", default="40", help="sizes of the simulated networks ('' for none)")
    r.add_argument("--network-seeds", default="0")
    r.add_argument("--seeds", default="0-4", help="sampler seeds (BatchParams.seed), e.g. 0-4 or 0,3")
    c = sub.add_parser("compare")
    c.add_argument("runs", nargs="+")
    args = ap.parse_args(argv)
    if args.cmd == "run":

        def ints(text: str) -> list[int]:
            out: list[int] = []
            for part in filter(None, text.split(",")):
                a, _, b = part.partition("-")
                out.extend(range(int(a), int(b) + 1) if b else [int(a)])
            return out

        names = [n for n in args.datasets.split(",") if n]
        samplers = args.samplers.split(",")
        if args.label and len(samplers) > 1:
            ap.error("--label names one sampler's rows")
        run(args.out, names, samplers, ints(args.nodes), ints(args.network_seeds), ints(args.seeds), args.label)
    else:
        compare(args.runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
