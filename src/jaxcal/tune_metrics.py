"""Pure reductions of the PGP filter's outputs shared by tuning, its checks and sweeps.

Windows of a dataset, the truth in filter order, the RMSEs over node-epochs, and the negative log
predictive likelihood of the ranges (the `evidence` objective; see `jaxcal.tune`).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxcal.data import MeshDataset
from jaxcal.errors import JaxcalError
from jaxcal.mesh import pgp
from jaxcal.mesh.frame import to_frame

__all__ = [
    "window",
    "truth_in_filter_order",
    "track_rmse",
    "final_rmse",
    "neg_log_predictive",
    "grid_span_m",
]


def window(dataset: MeshDataset, epochs: int | None) -> MeshDataset:
    """The first `epochs` epochs of a mesh dataset (all of them when None or larger)."""
    if epochs is None or epochs >= dataset.n_epochs:
        return dataset
    if epochs < 1:
        raise JaxcalError(f"epochs: must be >= 1, got {epochs}")
    k = int(epochs)
    opt = {f: getattr(dataset, f)[:k] for f in ("fp_rssi", "rx_rssi") if getattr(dataset, f) is not None}
    return dataclasses.replace(dataset, time=dataset.time[:k], range=dataset.range[:k], **opt)


def truth_in_filter_order(dataset: MeshDataset, config: str | None, order: np.ndarray) -> np.ndarray:
    """(N, 2) true positions in the configuration frame, rows in filter order; NaN when unknown.

    As `metrics.truth_in_result_frame`: the frame is built in 3-D when the truth is 3-D, then x, y.
    """
    n = dataset.n_nodes
    if dataset.truth is None:
        return np.full((n, 2), np.nan)
    a0, a1, a2 = dataset.config(config)
    t = dataset.truth
    if not np.isfinite(t[[a0, a1, a2]]).all():
        return np.full((n, 2), np.nan)
    return to_frame(t, a0, a1, a2)[:, :2][order]


def track_rmse(est: Float[Array, "epochs nodes 2"], truth: Float[Array, "nodes 2"]) -> Float[Array, ""]:
    """RMSE [m] over every finite (epoch, node) estimate except node 0 (a0) with a known truth.

    Differentiable: missing estimates are replaced before squaring, so their NaN never reaches a
    gradient. NaN when no estimate counts.
    """
    ok = jnp.isfinite(est).all(-1) & jnp.isfinite(truth).all(-1)[None, :]
    ok = ok.at[:, 0].set(False)
    t = jnp.where(jnp.isfinite(truth), truth, 0.0)
    e = jnp.where(ok[..., None], est, t[None]) - t[None]
    cnt = jnp.sum(ok)
    mse = jnp.sum(e * e) / jnp.maximum(cnt, 1)
    return jnp.where(cnt > 0, jnp.sqrt(jnp.where(cnt > 0, mse, 1.0)), jnp.nan)


def final_rmse(est: Float[Array, "epochs nodes 2"], truth: Float[Array, "nodes 2"]) -> Float[Array, ""]:
    """RMSE [m] of the last epoch's estimates, a0 excluded (`final_rmse_m` of `jaxcal evaluate`)."""
    return track_rmse(est[-1:], truth)


def neg_log_predictive(
    out: pgp.FilterOut, sigma_r: Float[Array, ""], p_out: Float[Array, ""], span_m: float
) -> Float[Array, ""]:
    """Negative log predictive likelihood of the ranges [nats per range factor] (module docstring).

    Args:
        out: per-epoch filter outputs (`log_evidence`, `n_factors` of shape (K, N)).
        sigma_r: range std [m]. p_out: floor weight. span_m: L, support of the range density [m].

    Returns:
        `-(sum log_evidence - n_factors log Z) / sum n_factors`; NaN when no range was used.
    """
    log_z = jnp.log((1.0 - p_out) * sigma_r * math.sqrt(2 * math.pi) + p_out * span_m)
    n = jnp.sum(out.n_factors)
    total = jnp.sum(out.log_evidence) - n * log_z
    return jnp.where(n > 0, -total / jnp.maximum(n, 1.0), jnp.nan)


def grid_span_m(cfg: pgp.FilterConfig) -> float:
    """L of the evidence density: the longest distance between two cells of the grid [m]."""
    return 2.0 * math.sqrt(2.0) * cfg.grid.n_half * cfg.grid.cell_m
