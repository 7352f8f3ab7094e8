"""Live calibration: a running filter fed chunk by chunk (`start`, `advance`), its posterior on demand."""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from jaxcal.errors import JaxcalError
from jaxcal.mesh import grid as G
from jaxcal.mesh.pgp.epochs import run_scan
from jaxcal.mesh.pgp.params import PGPParams, validate_params
from jaxcal.mesh.pgp.setup import node_order, setup_filter, symmetric_ranges
from jaxcal.mesh.pgp.state import FilterConfig, FilterInputs, FilterParams, FilterState, full_logpost, init_state
from jaxcal.params import with_overrides

__all__ = ["PGPStream", "start", "advance", "stream_posterior"]


class PGPStream(eqx.Module):
    """A running filter fed chunk by chunk (`start`, `advance`): live calibration.

    Attributes:
        cfg, prm: static configuration and numeric parameters. inp: constant inputs (masks,
            neighbour sets; its `z`, `dt` are unused). state: the filter state after `epochs`
            epochs. order: `order[k]` is the dataset index of filter node k. epochs: epochs done.
    """

    cfg: FilterConfig
    prm: FilterParams
    inp: FilterInputs
    state: FilterState
    order: tuple[int, ...] = eqx.field(static=True)
    epochs: int = eqx.field(static=True, default=0)


def start(
    n_nodes: int,
    params: PGPParams | dict | None = None,
    anchors=(0, 1, 2),
    radius_m: float | None = None,
    *,
    mode: str = "pgp",
) -> PGPStream:
    """Start a filter for live use: no epochs yet.

    Args:
        n_nodes: N, the number of nodes (dataset order; ranges fed later are (k, N, N)).
        params: a `PGPParams` or dict of overrides. anchors: (a0, a1, a2) node indices.
        radius_m: half-width of the grid [m] (None: `params.extent_m`; `run_pgp` sizes it from the
            ranges with `grid.extent_radius`, which needs the recording first).
        mode: "pgp" or "parametric".

    Returns:
        a `PGPStream` to pass to `advance`.
    """
    if not isinstance(params, PGPParams):
        params = with_overrides(PGPParams(), params)
    validate_params(params)
    order = node_order(int(n_nodes), anchors)
    radius = params.extent_m if radius_m is None else float(radius_m)
    if not (math.isfinite(radius) and radius > 0):
        raise JaxcalError(f"radius_m must be a positive number, got {radius_m!r}")
    grid = G.make_grid(radius, params.cell_m)
    n = int(n_nodes)
    cfg, prm, inp, lp0 = setup_filter(params, grid, n, mode, np.zeros(0), np.zeros((0, n, n)), np.zeros(0))
    return PGPStream(cfg, prm, inp, init_state(cfg, lp0), tuple(int(i) for i in order), 0)


def advance(stream: PGPStream, ranges: np.ndarray, dt: np.ndarray) -> tuple[PGPStream, np.ndarray]:
    """Feed the next epochs to a running filter.

    Advancing in chunks gives the same estimates as one run over all epochs (each chunk length
    compiles once: feed chunks of a fixed size for live use).

    Args:
        stream: from `start` or a previous `advance`.
        ranges: (k, N, N) ranges [m] of the next k epochs, dataset node order, NaN missing.
        dt: (k,) time step of each epoch to the one before [s] (0 for the very first).

    Returns:
        (stream, estimates): the advanced stream and (k, N, 2) eq. (13)/(14) estimates [m] in the
        configuration frame, dataset node order, NaN while a node is not localised.
    """
    r = np.asarray(ranges, dtype=np.float64)
    d = np.asarray(dt, dtype=np.float64)
    n = len(stream.order)
    if r.ndim != 3 or r.shape[1:] != (n, n) or d.shape != r.shape[:1]:
        raise JaxcalError(f"advance: need ranges (k, {n}, {n}) and dt (k,), got {r.shape}, {d.shape}")
    order = np.asarray(stream.order)
    z = symmetric_ranges(r)[:, order][:, :, order]
    dtype = stream.state.logpost.dtype
    inp = dataclasses.replace(stream.inp, z=jnp.asarray(z, dtype), dt=jnp.asarray(d, dtype))
    k0 = jnp.asarray(stream.epochs, jnp.int32)  # an array: no recompilation per chunk
    st, out = run_scan(stream.cfg, stream.prm, inp, stream.state, k0)
    est = np.asarray(out.estimate, dtype=np.float64)[:, np.argsort(order)]
    new = PGPStream(stream.cfg, stream.prm, stream.inp, st, stream.order, stream.epochs + r.shape[0])
    return new, est


def stream_posterior(stream: PGPStream) -> np.ndarray:
    """(N, n, n) current posterior probabilities on the stream's grid, dataset node order."""
    lp = np.asarray(full_logpost(stream.cfg, stream.state), dtype=np.float64)
    return np.exp(lp)[np.argsort(np.asarray(stream.order))]
