"""PGP speed: the fast path (`likelihood="window"`) against the direct evaluation of eq. (11).

Prints one JSON line per (nodes, cell size):

    .venv/bin/python benchmarks/pgp_speed.py --quick      # 12-node torgau at 0.25 m only
    .venv/bin/python benchmarks/pgp_speed.py              # 12/24/48 nodes x 0.5/0.25/0.1 m

Keys: nodes, epochs, cells, cell_m, window_cells (W; the windows are W x W), small_window_cells
(the small windows tried first), hypotheses (max_hyp), pairs (pairs with a range per epoch, mean),
device, compile_s (first call - best call of the fast path, whose chunk programs compile on first
use), epochs_per_s (fast path over all `epochs`, best of `--repeats`, block_until_ready, compile
apart), windowed_epochs (of which small_window_epochs ran on the small windows),
reference_epochs_per_s (the direct evaluation, `likelihood="direct"`, identical parameters and
grid, on the first `ref_epochs` epochs), speedup (their ratio), rmse_diff_m and max_pos_diff_m
(final-epoch RMSE against the truth and largest position difference, fast vs direct, both over the
first `ref_epochs` epochs), ref_windowed_epochs (windowed epochs within those), loadavg
(`os.getloadavg()` when the row finished) and cpus.

Scenarios: 12 nodes is `data/torgau.h5` (the simulated torgau scenario, seed 0) when present, else
`simulate("torgau", 0)`. The simulator has no 24- or 48-node scenario: those rows add 12 or 36
nodes at random positions (seed 1, >= 2 m apart) to the torgau hall, with torgau's walls, channel,
never-measured and outlier pairs and `conf1` frame, through `simulate(..., node_ids=, positions=)`.
Rows with 24 and 48 nodes run `--scale-epochs` epochs (the direct reference at 0.1 m with 48
nodes costs minutes per epoch on a 2-core CPU); rows at cells below 0.25 m run at most 2 repeats
(the direct reference once).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import dataclasses  # noqa: E402

import numpy as np  # noqa: E402

from jaxcal.errors import JaxcalError  # noqa: E402
from jaxcal.mesh import pgp  # noqa: E402
from jaxcal.mesh.frame import to_frame  # noqa: E402
from jaxcal.params import parse_set, with_overrides  # noqa: E402
from jaxcal.sim.mesh import SCENARIOS, simulate  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def scenario(nodes: int, epochs: int):
    """The mesh dataset of `nodes` nodes and its first `epochs` epochs (see the module doc)."""
    if nodes == 12:
        path = ROOT / "data" / "torgau.h5"
        if path.exists():
            from jaxcal.io import hdf5

            ds = hdf5.read(path)
        else:
            ds = simulate("torgau", 0)
    else:
        base = SCENARIOS["torgau"]
        rng = np.random.default_rng(1)
        pts = [np.asarray(p, float) for p in base.positions]
        w, h = base.hall
        while len(pts) < nodes:
            q = rng.uniform((0.05 * w, 0.05 * h), (0.95 * w, 0.95 * h))
            if all(np.hypot(*(q - p)) >= 2.0 for p in pts):
                pts.append(q)
        ids = tuple(base.node_ids) + tuple(f"S{k:02d}" for k in range(nodes - 12))
        ds = simulate("torgau", 0, node_ids=ids, positions=tuple(map(tuple, pts)), n_epochs=epochs)
    k = min(epochs, ds.n_epochs)
    return dataclasses.replace(ds, time=ds.time[:k], range=ds.range[:k])


def slice_inputs(inp, k):
    return dataclasses.replace(inp, z=inp.z[:k], dt=inp.dt[:k])


def best_time(fn, repeats):
    best = math.inf
    out = None
    for _ in range(repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t)
    return best, out


def final_rmse(est, truth):
    ok = np.isfinite(est).all(1) & np.isfinite(truth).all(1)
    ok[0] = False  # a0 is the origin by construction
    return float(np.sqrt(np.mean(np.sum((est[ok] - truth[ok]) ** 2, axis=1))))


def row(nodes, cell_m, epochs, ref_epochs, repeats, config="conf1", overrides=None):
    ds = scenario(nodes, epochs)
    a = ds.config(config)
    p = with_overrides(pgp.PGPParams(cell_m=cell_m), overrides or {})
    cfg, prm, inp, lp0, order = pgp.prepare(ds, p, config)
    # the fast path is driven from the host in chunks (`pgp.run_chunked`, what `run_pgp` runs):
    # it compiles a few chunk programs on first use, so compile_s = first call - best call
    t = time.perf_counter()
    jax.block_until_ready(pgp.run_chunked(cfg, prm, inp, lp0))
    first_s = time.perf_counter() - t
    fast_s, (_, out) = best_time(lambda: pgp.run_chunked(cfg, prm, inp, lp0), repeats)
    compile_s = max(first_s - fast_s, 0.0)
    run = jax.jit(pgp.filter_epochs)

    k = min(ref_epochs, ds.n_epochs)
    cfg_d, prm_d, inp_d, lp0_d, _ = pgp.prepare(ds, dataclasses.replace(p, likelihood="direct"), config)
    assert cfg_d.grid == cfg.grid
    sub_d, sub_f = slice_inputs(inp_d, k), slice_inputs(inp, k)
    ref = run.lower(cfg_d, prm_d, sub_d, lp0_d).compile()
    ref_s, (_, out_d) = best_time(lambda: ref(cfg_d, prm_d, sub_d, lp0_d), max(1, repeats - 1))
    _, out_f = jax.block_until_ready(pgp.run_chunked(cfg, prm, sub_f, lp0))

    truth = to_frame(np.asarray(ds.truth, float)[:, :2], *a)[order]
    e_f = np.asarray(out_f.estimate[-1])
    e_d = np.asarray(out_d.estimate[-1])
    both = np.isfinite(e_f).all(1) & np.isfinite(e_d).all(1)
    z = np.asarray(inp.z)
    eps, ref_eps = ds.n_epochs / fast_s, k / ref_s
    return {
        "nodes": nodes,
        "epochs": int(ds.n_epochs),
        "cells": int(cfg.grid.n_cells),
        "cell_m": cell_m,
        "window_cells": int(cfg.window),
        "hypotheses": int(cfg.n_hyp),
        "pairs": float(np.isfinite(z).sum() / z.shape[0]),
        "device": f"{jax.devices()[0].platform}: {jax.devices()[0].device_kind}",
        "compile_s": round(compile_s, 2),
        "epochs_per_s": round(eps, 2),
        "windowed_epochs": int(np.asarray(out.windowed).sum()),
        "small_window_epochs": int(np.asarray(out.small).sum()),
        "small_window_cells": int(cfg.window_small),
        "reference_epochs_per_s": round(ref_eps, 4),
        "ref_epochs": int(k),
        "ref_windowed_epochs": int(np.asarray(out_f.windowed).sum()),
        "speedup": round(eps / ref_eps, 1),
        "rmse_diff_m": abs(final_rmse(e_f, truth) - final_rmse(e_d, truth)),
        "max_pos_diff_m": float(np.max(np.linalg.norm(e_f[both] - e_d[both], axis=1))) if both.any() else float("nan"),
        "loadavg": [round(x, 2) for x in os.getloadavg()],
        "cpus": os.cpu_count(),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only 12 nodes at 0.25 m (< 2 min)")
    ap.add_argument("--nodes", default="12,24,48")
    ap.add_argument("--cells", default="0.5,0.25,0.1")
    ap.add_argument("--epochs", type=int, default=2000, help="epochs of the 12-node rows")
    ap.add_argument("--scale-epochs", type=int, default=300, help="epochs of 24/48-node rows")
    ap.add_argument("--ref-epochs", type=int, default=20, help="epochs of the direct reference")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="PGP parameter override for every row (e.g. window_small_m=3.5)",
    )
    a = ap.parse_args(argv)
    with_overrides(pgp.PGPParams(), parse_set(a.set))  # bad overrides fail before any row runs
    if a.quick:
        rows = [(12, 0.25)]
        a.repeats = min(a.repeats, 2)
        a.ref_epochs = min(a.ref_epochs, 10)
    else:
        rows = [(int(n), float(c)) for n in a.nodes.split(",") for c in a.cells.split(",")]
    for nodes, cell in rows:
        epochs = a.epochs if nodes == 12 else a.scale_epochs
        repeats = a.repeats if cell >= 0.25 else min(a.repeats, 2)
        # the direct reference costs ~ pairs x cells per epoch: fewer epochs where it is slow
        scale = (cell / 0.25) ** 2 * (12 / nodes) ** 2
        ref = min(a.ref_epochs, max(8, int(a.ref_epochs * scale)))
        rec = row(nodes, cell, epochs, ref, repeats, overrides=parse_set(a.set))
        print(json.dumps({**rec, "set": a.set}), flush=True)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (JaxcalError, ValueError) as e:  # bad --set values: one line, no traceback
        sys.exit(f"pgp_speed: error: {e}")
