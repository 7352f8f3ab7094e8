"""Host-side setup of the filter: symmetric ranges, neighbour sets, node order, the grid and the
arrays of `FilterConfig` / `FilterParams` / `FilterInputs` (`prepare`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxcal.data import MeshDataset
from jaxcal.errors import JaxcalError
from jaxcal.mesh import fast as F
from jaxcal.mesh import grid as G
from jaxcal.mesh.pgp.params import NUMERIC, PGPParams, validate_params
from jaxcal.mesh.pgp.state import FilterConfig, FilterInputs, FilterParams

__all__ = ["symmetric_ranges", "neighbour_sets", "node_order", "filter_params", "setup_filter", "prepare"]


def symmetric_ranges(ranges: np.ndarray) -> np.ndarray:
    """(K, N, N) ranges -> symmetric: mean of i->j and j->i where both exist, else the one there."""
    r = ranges
    rt = np.swapaxes(r, 1, 2)
    both = np.isfinite(r) & np.isfinite(rt)
    out = np.where(both, 0.5 * (r + rt), np.where(np.isfinite(r), r, rt))
    n = r.shape[1]
    out[:, np.arange(n), np.arange(n)] = np.nan
    return out


def neighbour_sets(params: PGPParams, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(allowed (N, N), need (N,)) for `n` nodes in filter order: structural neighbours (eq. 5, 6, 11) and the
    localised neighbours each node must hear before it is localised."""
    allowed = np.ones((n, n), dtype=bool)
    np.fill_diagonal(allowed, False)
    allowed[0] = False
    allowed[1] = False
    allowed[1, 0] = True
    if not params.a2_all:
        allowed[2] = False
        allowed[2, :2] = True
    need = np.full(n, float(params.min_refs))
    need[:3] = (0.0, 1.0, 2.0)
    return allowed, need


def filter_params(params: PGPParams) -> FilterParams:
    """The numeric fields of `params` (`NUMERIC`) as the filter's arrays (the default float type)."""
    ftype = jnp.result_type(float)
    return FilterParams(*(jnp.asarray(getattr(params, f), ftype) for f in NUMERIC))


def setup_filter(
    params: PGPParams,
    grid: G.Grid,
    n: int,
    mode: str,
    snapshots: np.ndarray,
    ranges: np.ndarray,
    dt: np.ndarray,
) -> tuple[FilterConfig, FilterParams, FilterInputs, Float[Array, "nodes nx ny"]]:
    """(config, params, inputs, logpost0) for `n` nodes in filter order on `grid` (host side), from
    (epochs, n, n) symmetric `ranges` in filter order, (epochs,) time steps `dt` [s] and the
    snapshot epochs."""
    z, snaps = ranges, snapshots
    mask = G.region_masks(grid, n)
    allowed, need = neighbour_sets(params, n)
    ftype = jnp.result_type(float)
    window = window_small = 0
    if params.likelihood == "window" and params.update_order == "jacobi":
        window = F.window_side(params.window_m, grid)
        if window * window < params.top_k or grid.n_side < params.top_k:
            window = 0  # the windows (and a1's row) must hold the top_k cells of eq. (7)
        small = F.window_side(params.window_small_m, grid) if params.window_small_m > 0 else 0
        if window and small * small >= params.top_k and small < window:
            window_small = small
    cfg = FilterConfig(
        grid=grid,
        top_k=min(params.top_k, grid.n_cells),
        n_hyp=min(params.max_hyp, grid.n_cells),
        update_order=params.update_order,
        smoothing=params.smoothing,
        median_window=params.median_window,
        mode=mode,
        n_snap=int(snaps.size),
        likelihood="direct" if params.likelihood in ("window", "sparse") else params.likelihood,
        window=window,
        window_small=window_small,
        range_model=params.range_model,
    )
    prm = filter_params(params)
    inp = FilterInputs(
        z=jnp.asarray(z, ftype),
        dt=jnp.asarray(dt, ftype),
        mask=jnp.asarray(mask),
        allowed=jnp.asarray(allowed),
        need=jnp.asarray(need, ftype),
        snap_at=jnp.asarray(snaps, ftype),
    )
    logpost0 = jnp.where(inp.mask, 0.0, -jnp.inf).astype(ftype)
    logpost0 = logpost0 - jax.nn.logsumexp(logpost0, axis=(1, 2), keepdims=True)
    return cfg, prm, inp, logpost0


def node_order(n: int, anchors) -> np.ndarray:
    """(n,) filter order of `n` nodes: `order[k]` is the dataset index of filter node k, the frame's
    (a0, a1, a2) = `anchors` first, then the others in dataset order; one-line error unless the
    anchors are three distinct indices in [0, n)."""
    a0, a1, a2 = (int(a) for a in anchors)
    if len({a0, a1, a2}) != 3 or min(a0, a1, a2) < 0 or max(a0, a1, a2) >= n:
        raise JaxcalError(f"anchors must be three distinct node indices in [0, {n}), got {anchors}")
    return np.array([a0, a1, a2] + [i for i in range(n) if i not in (a0, a1, a2)])


def prepare(
    dataset: MeshDataset,
    params: PGPParams,
    config: str | None,
    mode: str = "pgp",
    snapshot_epochs=(),
    anchors=None,
) -> tuple[FilterConfig, FilterParams, FilterInputs, Float[Array, "nodes nx ny"], np.ndarray]:
    """Host-side setup: node order, grid, masks and arrays for `filter_epochs` (and every other
    filter driver: `scan`, `run_chunked`, ...).

    `anchors` (a0, a1, a2) overrides the configuration's frame (the proxy frame of `run_pgp`).

    Returns:
        (config, params, inputs, logpost0, order): `FilterConfig`, `FilterParams`, `FilterInputs`
        (nodes in filter order), (nodes, nx, ny) initial log posteriors, and (nodes,) `order`
        where `order[k]` is the dataset index of filter node k.
    """
    validate_params(params)
    n = dataset.n_nodes
    order = node_order(n, dataset.config(config) if anchors is None else anchors)
    z = symmetric_ranges(np.asarray(dataset.range, dtype=np.float64))[:, order][:, :, order]
    radius = G.extent_radius(z, 0, params.margin_m, params.extent_m)
    grid = G.make_grid(radius, params.cell_m)
    t = np.asarray(dataset.time, dtype=np.float64)
    dt = np.diff(t, prepend=t[:1]) if t.size else t
    snaps = np.asarray(sorted({int(s) for s in snapshot_epochs}), dtype=np.float64)
    if snaps.size and (snaps.min() < 0 or snaps.max() >= max(dataset.n_epochs, 1)):
        raise JaxcalError(f"snapshot epochs must lie in [0, {dataset.n_epochs})")
    cfg, prm, inp, logpost0 = setup_filter(params, grid, n, mode, snaps, z, dt)
    return cfg, prm, inp, logpost0, order
