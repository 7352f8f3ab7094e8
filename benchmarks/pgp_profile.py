"""Where `calibrate --method pgp` spends its time on a large network (issue #26): stage times.

One process: imports, the simulated network (`jaxcal.sim.network`, seed, 200 epochs), then
`pgp.calibrate` twice: cold (compilations included) and warm (the same programs from the in-process
cache), so compilation = cold - warm per stage. Stages (host clock, CPU time of the process beside):
the offset pass (`bias`: the first run on `OFFSET_EPOCHS` epochs; node-local grids only), the offset
fit, the filter's chunks of 25 epochs (`progress` callback: the first chunk holds the compilation and
the nodes' wide grids before they localise), the final covariance and scatter, and calibrate's
pair covariance and identifiability mask. Prints one JSON line per pass and a Markdown table.

Usage:
    python benchmarks/pgp_profile.py --nodes 100 [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

T_START = (time.perf_counter(), time.process_time())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    from jaxcal.mesh import masking, pgp, range_offset
    from jaxcal.sim.mesh import simulate
    from jaxcal.sim.network import network_scenario

    marks: list[tuple[str, float, float]] = []

    def mark(name):
        marks.append((name, time.perf_counter(), time.process_time()))

    t_imp = (time.perf_counter() - T_START[0], time.process_time() - T_START[1])
    ds = simulate(network_scenario(a.nodes, seed=a.seed, n_epochs=200), seed=a.seed)
    t_sim = (time.perf_counter() - T_START[0] - t_imp[0], time.process_time() - T_START[1] - t_imp[1])
    print(json.dumps({"imports_s": [round(x, 2) for x in t_imp], "simulate_s": [round(x, 2) for x in t_sim]}))

    def timed(mod, name, label):
        f = getattr(mod, name)

        def g(*args, **kw):
            mark(f"before {label}")
            out = f(*args, **kw)
            mark(label)
            return out

        setattr(mod, name, g)

    # the offset pass ends where the fit starts; the second pass's chunks come from `progress`
    timed(range_offset, "fit_offset", "offset fit")
    timed(pgp, "with_pair_covariance", "pair covariance")
    timed(masking, "mask_result", "identifiability mask")
    rows = []
    for run in ("cold", "warm"):
        marks.clear()
        mark("start")
        chunks = []
        res = pgp.calibrate(
            ds, None, "conf1", progress=lambda m, c=chunks: c.append((time.perf_counter(), time.process_time()))
        )
        mark("end")
        t = {name: (w, c) for name, w, c in marks}
        w0, c0 = t["start"]
        stages = []
        if "before offset fit" in t:
            stages.append(("offset pass (first run, 50 epochs)", t["before offset fit"], (w0, c0)))
            stages.append(("offset fit", t["offset fit"], t["before offset fit"]))
            prev = t["offset fit"]
        else:
            prev = (w0, c0)
        for k, ch in enumerate(chunks):
            stages.append((f"filter epochs {25 * k}-{25 * k + 24}", ch, prev))
            prev = ch
        stages.append(("final covariance, result", t["before pair covariance"], prev))
        stages.append(("pair covariance", t["pair covariance"], t["before pair covariance"]))
        stages.append(("identifiability mask", t["identifiability mask"], t["before identifiability mask"]))
        stages.append(("total", t["end"], (w0, c0)))
        row = {"run": run, "nodes": a.nodes, "seed": a.seed, "placed": int(np.isfinite(res.position).all(1).sum())}
        row["stages"] = {name: [round(e[0] - s[0], 2), round(e[1] - s[1], 2)] for name, e, s in stages}
        rows.append(row)
        print(json.dumps(row), flush=True)
    print(f"\nimports {t_imp[0]:.2f} s wall / {t_imp[1]:.2f} s CPU; simulate {t_sim[0]:.2f} / {t_sim[1]:.2f} s")
    print("| stage | cold wall [s] | cold CPU [s] | warm wall [s] | warm CPU [s] |")
    print("|---|---|---|---|---|")
    for name in rows[0]["stages"]:
        c, w = rows[0]["stages"][name], rows[1]["stages"].get(name, [float("nan")] * 2)
        print(f"| {name} | {c[0]} | {c[1]} | {w[0]} | {w[1]} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
