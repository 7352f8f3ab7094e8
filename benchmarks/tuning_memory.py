"""Memory of the tuning gradient: one scan (every epoch's carry kept) vs checkpointed segments.

Compiles `jax.grad` of the `nlpl` objective for the first K epochs of simulated torgau (conf1) and
reads XLA's buffer assignment (`compiled.memory_analysis()`: temporaries + arguments + outputs,
bytes); nothing is run. `segment=K` is the one-scan filter with every epoch checkpointed (K carries
kept for the backward pass); `segment=None` is ceil(sqrt(K)) epochs per segment. One JSON line per
(K, segment).

    PYTHONPATH=src python benchmarks/tuning_memory.py [--cell 1.0] [--epochs 100,400]
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

from jaxcal import tune as T  # noqa: E402
from jaxcal.mesh.pgp import PGPParams  # noqa: E402
from jaxcal.mesh.segmented import segment_length  # noqa: E402
from jaxcal.sim.mesh import simulate  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cell", type=float, default=1.0)
    ap.add_argument("--epochs", default="100,400")
    a = ap.parse_args()
    full = simulate("torgau", 0)
    for k in (int(x) for x in a.epochs.split(",")):
        ds = T.window(full, k)
        for seg in (k, None):
            prob, _ = T.make_problem(ds, PGPParams(cell_m=a.cell), "conf1", "nlpl", segment=seg)
            theta = T.theta_of(0.3, 0.25, 0.9, jnp.float64)
            c = jax.jit(jax.grad(T.objective)).lower(theta, prob).compile()
            m = c.memory_analysis()
            total = m.temp_size_in_bytes + m.argument_size_in_bytes + m.output_size_in_bytes
            print(
                json.dumps(
                    {
                        "epochs": k,
                        "segment": seg or segment_length(k),
                        "cell_m": a.cell,
                        "cells_side": prob.cfg.grid.n_side,
                        "temp_mb": m.temp_size_in_bytes / 2**20,
                        "total_mb": total / 2**20,
                        "carry_mb": prob.logpost0.size * 8 / 2**20,
                        "loadavg": os.getloadavg()[0],
                    }
                ),
                flush=True,
            )


if __name__ == "__main__":
    main()
