"""Cost of the tuning gradient against the forward pass (issue 17: reverse mode was ~65x forward).

Times the soft-cut objective of `jaxcal.tune` (checkpointed segments, calibrate's
`likelihood="window"` path, float64) and its `jax.value_and_grad` on the first K epochs of
simulated torgau (conf1), each jitted, the second call timed (the first is reported as compile +
run). Run it once with this tree's `src` and once with an older one on PYTHONPATH to compare
(same machine, one after the other). One JSON line per run, the gradient included (the two trees
must agree on it).

    PYTHONPATH=src python benchmarks/tuning_grad_cost.py [--epochs 200] [--cell 0.5]
        [--objective nlpl]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

from jaxcal import tune as T  # noqa: E402
from jaxcal.mesh.pgp import PGPParams  # noqa: E402
from jaxcal.sim.mesh import simulate  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--epochs", type=int, default=200)
    ap.add_argument("--cell", type=float, default=0.5)
    ap.add_argument("--objective", default="nlpl")
    a = ap.parse_args()
    ds = T.window(simulate("torgau", 0), a.epochs)
    prob, _ = T.make_problem(ds, PGPParams(cell_m=a.cell), "conf1", a.objective)
    theta = T.theta_of(0.3, 0.25, 0.9, jnp.float64)
    row = {"epochs": a.epochs, "cell_m": a.cell, "objective": a.objective, "src": T.__file__}
    for name, fn in (("forward", jax.jit(T.objective)), ("value_and_grad", jax.jit(jax.value_and_grad(T.objective)))):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(theta, prob))
        t1 = time.perf_counter()
        out = jax.block_until_ready(fn(theta, prob))
        t2 = time.perf_counter()
        row[f"{name}_first_s"] = round(t1 - t0, 2)
        row[f"{name}_s"] = round(t2 - t1, 3)
        if name == "value_and_grad":
            row["value"] = float(out[0])
            row["grad"] = [float(g) for g in out[1]]
    row["ratio"] = round(row["value_and_grad_s"] / row["forward_s"], 2)
    row["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    row["loadavg"] = round(os.getloadavg()[0], 1)
    print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
