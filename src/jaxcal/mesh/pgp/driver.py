"""PGP on a mesh dataset: `run_pgp` (global grid, or node-local grids on large sites, `local.py`; the
range-offset pass of `bias`; the proxy frame of `frame`), `calibrate` (`--method pgp`) and the pair-level
covariance it reports (`with_pair_covariance`)."""

from __future__ import annotations

import dataclasses
import logging
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.data import MeshDataset, Result
from jaxcal.errors import JaxcalError
from jaxcal.mesh import grid as G
from jaxcal.mesh import local as L
from jaxcal.mesh.pgp.epochs import run_chunked
from jaxcal.mesh.pgp.mirror import resolve_mirrors, span_undecided
from jaxcal.mesh.pgp.params import OFFSET_EPOCHS, PGPParams, validate_params
from jaxcal.mesh.pgp.setup import filter_params, neighbour_sets, node_order, prepare, symmetric_ranges
from jaxcal.mesh.pgp.state import PGPInfo
from jaxcal.params import as_dict, with_overrides

__all__ = [
    "run_pgp",
    "calibrate",
    "with_pair_covariance",
    "cell_variance",
    "uses_local",
    "local_site",
    "local_setup",
    "global_grid_only",
    "software_version",
]


def cell_variance(cell_m: float, n: int, anchors: tuple[int, int, int]) -> np.ndarray:
    """(n, 2, 2) within-cell variance cell^2 / 12 per free axis (a0: none; a1: x only).

    The grid posterior puts each cell's probability on its centre; read as a histogram density
    (uniform within each cell), its covariance is the centres' covariance plus cell^2 / 12 on each
    axis the node is free in. Without it a node whose posterior sits in one cell reports a variance
    near 0 although it is only known to within a cell, and its NEES is far above 1 (the NEES with
    and without this term: the benchmarks page of the docs).
    """
    out = np.zeros((n, 2, 2))
    q = cell_m * cell_m / 12.0
    out[:, 0, 0] = out[:, 1, 1] = q
    out[anchors[0]] = 0.0
    out[anchors[1], 1, 1] = 0.0
    return out


def run_pgp(
    dataset: MeshDataset,
    params: PGPParams | dict | None = None,
    config: str | None = None,
    *,
    mode: str = "pgp",
    snapshot_epochs=(),
    progress=None,
    posterior: bool = True,
) -> tuple[Result, PGPInfo]:
    """Run the grid filter on a mesh dataset.

    Args:
        dataset: the mesh recording (K epochs, N nodes).
        params: a `PGPParams` or a dict of overrides of its defaults (strings are cast).
        config: the frame configuration's name (None: `default` or (0, 1, 2)).
        mode: "pgp" (eq. 10-11) or "parametric" (eq. 9).
        snapshot_epochs: epochs whose posterior grids are returned in `PGPInfo.snapshots`.
        progress: optional callback, called with the epochs done since its last call (the scan
            runs in chunks; results do not depend on it).
        posterior: fill `PGPInfo.posterior` (with node-local grids, `grid_mode`, that is an
            (N, n, n) array on the whole lattice, built for inspection; False: an empty array).

    Returns:
        (Result, PGPInfo): positions, covariance and per-epoch track in the configuration frame,
        and the
        posterior grids in the dataset's node order.
    """
    if not isinstance(params, PGPParams):
        params = with_overrides(PGPParams(), params)
    if dataset.n_epochs == 0:
        raise JaxcalError(f"{dataset.name}: no epochs to calibrate from")
    a = dataset.config(config)
    b = a if params.frame == "direct" else _filter_anchors(dataset, a, params.frame, params.min_refs, mode)
    validate_params(params)
    local = None
    if params.grid_mode != "global":
        local = local_setup(dataset, params, b, mode, bool(len(snapshot_epochs)))
    if params.bias == "network" or (params.bias == "auto" and local is not None):
        return _run_offset(dataset, params, config, mode, snapshot_epochs, progress, posterior, (a, b, local))
    if local is not None:
        return _run_local(dataset, params, a, b, local, progress, posterior)
    cfg, prm, inp, logpost0, order = prepare(dataset, params, config, mode, snapshot_epochs, b)
    st, out = run_chunked(cfg, prm, inp, logpost0, progress=progress)
    cells = cfg.grid.cells(logpost0.dtype)
    n = logpost0.shape[0]
    lp = st.logpost.reshape(n, -1)
    _, grid_cov = jax.vmap(G.mean_cov, in_axes=(0, None))(lp, cells)
    inv = np.argsort(order)
    est = np.asarray(out.estimate, dtype=np.float64)[:, inv]
    raw = np.asarray(out.raw, dtype=np.float64)[:, inv]
    loc_any = np.isfinite(est).all(axis=2).any(axis=0)
    final = est[-1]
    cov = np.asarray(grid_cov, dtype=np.float64)[inv]
    cov = cov + cell_variance(cfg.grid.cell_m, n, b)
    cov[~loc_any] = np.nan
    a = _report_frame(dataset, a, b, final, mode)
    if b != a:  # proxy frame: every epoch moved into the configuration's frame by its a0, a1, a2
        final, cov, est = _to_config_frame(final, cov, est, a)
        loc_any = np.isfinite(est).all(axis=2).any(axis=0)
    final, cov = _mirror_checked(dataset, params, a, final, cov, mode)
    res = _result(dataset, params, mode, a, final, cov, est)
    info = PGPInfo(
        axis_m=np.asarray(cfg.grid.axis(np.float64)),
        posterior=np.exp(np.asarray(st.logpost, dtype=np.float64))[inv],
        snapshot_epochs=np.asarray(inp.snap_at, dtype=np.int64),
        snapshots=np.exp(np.asarray(st.snaps, dtype=np.float64))[:, inv],
        log_mass=np.asarray(out.log_mass, dtype=np.float64)[:, inv],
        raw_track=raw,
        localised=np.asarray(loc_any),
        frame=f"anchors:{b[0]},{b[1]},{b[2]}",
    )
    return res, info


def uses_local(dataset: MeshDataset, params=None, config: str | None = None, mode: str = "pgp") -> bool:
    """Whether `run_pgp` (and so `calibrate`) runs `dataset` on node-local grids (`grid_mode`, `local.py`):
    tools that drive the global-grid filter themselves (tune, live, sweeps) check it."""
    if not isinstance(params, PGPParams):
        params = with_overrides(PGPParams(), params)
    if params.grid_mode == "global" or dataset.n_epochs == 0:
        return False
    a = dataset.config(config)
    b = a if params.frame == "direct" else _filter_anchors(dataset, a, params.frame, params.min_refs)
    return local_setup(dataset, params, b, mode, False) is not None


def global_grid_only(tool: str, site: str) -> JaxcalError:
    """The one-line refusal of a tool that runs the global grid only (`tool`: "tune", "live
    calibration") on a site where `calibrate` runs node-local grids (`uses_local`)."""
    return JaxcalError(
        f"{site}: the site is wider than one node-local grid, where calibrate --method pgp runs node-local "
        f"grids (grid_mode=auto), which {tool} does not run; use --set grid_mode=global here and for "
        "calibrate to run the global grid in both"
    )


def _run_offset(
    dataset: MeshDataset, params: PGPParams, config, mode, snapshot_epochs, progress, posterior: bool, where
):
    """`run_pgp` with `bias` "network" (or "auto" on node-local grids): a first run on the first
    `OFFSET_EPOCHS` epochs, the offset fitted to its positions (`range_offset.fit_offset`), then the run
    on every range minus the offset. The result's `params` are `params` (a rerun fits the same offset).
    `where`: (a, b, `local_setup` or None). On node-local grids both runs take the lattice, wide side
    and neighbour lists of the recording's own ranges (one compilation for both)."""
    from jaxcal.mesh.range_offset import fit_offset, pair_medians

    log = logging.getLogger("jaxcal")
    plain = dataclasses.replace(params, bias="none")
    r = np.asarray(dataset.range)
    k = min(OFFSET_EPOCHS, dataset.n_epochs)
    short = dataclasses.replace(dataset, time=np.asarray(dataset.time)[:k], range=r[:k], fp_rssi=None, rx_rssi=None)
    a, b, local = where

    def run(ds, z_run, prog, post, snaps=()):
        if local is None:
            return run_pgp(ds, plain, config, mode=mode, snapshot_epochs=snaps, progress=prog, posterior=post)
        order, z, dt, lattice, wide = local
        return _run_local(ds, plain, a, b, (order, z_run, dt[: z_run.shape[0]], lattice, wide), prog, post, setup_z=z)

    level = log.level
    log.setLevel(logging.ERROR)  # the first run's warnings (unplaced nodes...) are the second run's to give
    try:
        first, _ = run(short, None if local is None else local[1][:k], None, False)
    finally:
        log.setLevel(level)
    z_run = None if local is None else local[1]
    c, pairs = fit_offset(np.asarray(first.position), pair_medians(symmetric_ranges(r)), params.sigma_r)
    if np.isfinite(c):
        log.info(
            "pgp: range offset %+.3f m fitted from %d pairs (bias=%s), subtracted from every range",
            c,
            pairs,
            params.bias,
        )
        shifted = np.where(np.isfinite(r), np.maximum(r - c, 0.0), r)
        dataset = dataclasses.replace(dataset, range=shifted)
        z_run = None if z_run is None else np.where(np.isfinite(z_run), np.maximum(z_run - c, 0.0), z_run)
    else:
        log.warning("pgp: range offset not fitted (too few pairs between placed nodes): ranges taken as unbiased")
    res, info = run(dataset, z_run, progress, posterior, snapshot_epochs)
    res = dataclasses.replace(res, params=as_dict(params))
    return res, dataclasses.replace(info, offset_m=c if np.isfinite(c) else float("nan"))


def _mirror_checked(dataset: MeshDataset, params: PGPParams, a, final, cov, method: str):
    """(final, cov) after the mirror check of `params.mirror` (`mirror.resolve_mirrors`): parts of the
    layout the filter locked in a mirror image moved to the image the ranges prefer. The track stays the
    filter's."""
    if params.mirror == "off":
        return final, cov
    return resolve_mirrors(dataset.range, dataset.node_ids, a, final, cov, params.sigma_r, method)


def _result(dataset: MeshDataset, params: PGPParams, method: str, a, final, cov, est) -> Result:
    """The `Result` of a filter run: final positions and covariances, the track, in the frame a0, a1, a2 = `a`."""
    return Result(
        ids=dataset.node_ids,
        position=final,
        method=method,
        dataset=dataset.name,
        frame=f"anchors:{a[0]},{a[1]},{a[2]}",
        params=as_dict(params),
        covariance=cov,
        track_time=np.asarray(dataset.time, dtype=np.float64),
        track_position=est,
        software=software_version(),
    )


def local_site(params: PGPParams, z: np.ndarray, anchors, mode: str = "pgp", snapshots: bool = False) -> bool:
    """Whether `run_pgp` takes node-local grids for (K, N, N) symmetric ranges `z` (`symmetric_ranges`)
    in the frame of `anchors`: `grid_mode`, and the global grid wider than one node-local grid."""
    if params.grid_mode == "global":
        return False
    wide = L.wide_side(z, params.margin_m, params.cell_m, params.local_m)
    full = G.make_grid(G.extent_radius(z, anchors[0], params.margin_m, params.extent_m), params.cell_m)
    return L.use_local(params, full.n_side, wide, mode, snapshots)


def local_setup(
    dataset: MeshDataset, params: PGPParams, anchors, mode: str, snapshots: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, G.Grid, int] | None:
    """What `run_pgp` runs on node-local grids (`local.py`) in the frame of `anchors` (a0, a1, a2), or
    None where it runs the global grid (`local_site`).

    Returns:
        (order, z, dt, lattice, wide): (N,) filter order (`node_order`), (K, N, N) symmetric ranges
        in filter order [m], (K,) time steps [s], the lattice `grid.Grid` and the wide grid's side
        [cells]; or None.
    """
    n = dataset.n_nodes
    order = node_order(n, anchors)
    z = symmetric_ranges(np.asarray(dataset.range, dtype=np.float64))[:, order][:, :, order]
    if not local_site(params, z, (0, 1, 2), mode, snapshots):
        return None
    wide = L.wide_side(z, params.margin_m, params.cell_m, params.local_m)
    radius = G.extent_radius(z, 0, params.margin_m, math.inf)
    radius = (wide // 2 + 1) * params.cell_m if not math.isfinite(radius) else radius
    lattice = G.make_grid(max(radius, (wide // 2 + 1) * params.cell_m), params.cell_m)
    t = np.asarray(dataset.time, dtype=np.float64)
    dt = np.diff(t, prepend=t[:1]) if t.size else t
    return order, z, dt, lattice, wide


def _run_local(dataset: MeshDataset, params: PGPParams, a, b, local, progress, posterior: bool, setup_z=None):
    """`run_pgp` on node-local grids (`local.py`): the same `Result` and `PGPInfo` (the lattice's axis,
    the posteriors placed on it when `posterior`; no snapshots). `setup_z`: the ranges that size the
    neighbour lists (default: `local`'s)."""
    order, z, dt, lattice, wide = local
    n = dataset.n_nodes
    allowed, need = neighbour_sets(params, n)
    cfg, kind, log_cells, nbrs = L.setup(params, n, z if setup_z is None else setup_z, allowed, lattice, wide)
    ftype = jnp.result_type(float)
    prm = filter_params(params)
    st, out, cov = L.run_local(
        cfg, prm, jnp.asarray(allowed), jnp.asarray(need, ftype), kind, log_cells, nbrs, z, dt, progress=progress
    )
    inv = np.argsort(order)
    est = np.asarray(out.estimate, dtype=np.float64)[:, inv]
    raw = np.asarray(out.raw, dtype=np.float64)[:, inv]
    loc_any = np.isfinite(est).all(axis=2).any(axis=0)
    final = est[-1]
    cov = np.asarray(cov, dtype=np.float64)[inv] + cell_variance(lattice.cell_m, n, b)
    cov[~loc_any] = np.nan
    a = _report_frame(dataset, a, b, final, "pgp")
    if b != a:
        final, cov, est = _to_config_frame(final, cov, est, a)
        loc_any = np.isfinite(est).all(axis=2).any(axis=0)
    final, cov = _mirror_checked(dataset, params, a, final, cov, "pgp")
    log = logging.getLogger("jaxcal")
    lost = int(np.asarray(out.lost).sum())
    if lost:  # a just-localised node whose top_k cells still include a far mode of tiny mass
        # the proven bound on the dropped mass; above 1 it bounds nothing (the mass itself is at most 1)
        frac = min(float(np.exp(np.nanmax(np.asarray(out.lost_log)))), 1.0)
        (log.warning if frac > 1e-3 else log.debug)(
            "pgp: in %d node-epochs up to %.1e (a bound) of a node's probability lay outside its %.0f m grid "
            "and was dropped",
            lost,
            frac,
            wide * lattice.cell_m,
        )
    never = [dataset.node_ids[i] for i in np.flatnonzero(~loc_any)]
    if never:
        log.warning(
            "pgp: %d node(s) never localised, left unplaced (NaN): %s (fewer than min_refs localised "
            "neighbours, or a posterior never within localise_m)",
            len(never),
            ", ".join(never[:10]) + (" ..." if len(never) > 10 else ""),
        )
    res = _result(dataset, params, "pgp", a, final, cov, est)
    post = L.scatter(cfg, st)[inv] if posterior else np.zeros((0, 0, 0))
    info = PGPInfo(
        axis_m=np.asarray(lattice.axis(np.float64)),
        posterior=post,
        snapshot_epochs=np.zeros((0,), np.int64),
        snapshots=np.zeros((0, n, 0, 0)),
        log_mass=np.zeros(est.shape[:2]),
        raw_track=raw,
        localised=np.asarray(loc_any),
        frame=f"anchors:{b[0]},{b[1]},{b[2]}",
    )
    return res, info


def _filter_anchors(dataset: MeshDataset, anchors, mode: str, min_refs: int = 3, say: str = "") -> tuple[int, int, int]:
    """The frame the filter runs in (`PGPParams.frame`: "auto" or "proxy"); `say`: the method's name, to
    say in one line (logger "jaxcal", info) why it is not the configuration's frame."""
    from jaxcal.mesh import frame_choice

    if mode == "proxy":
        best = frame_choice.choose_frame(dataset.range, min_refs=min_refs, need=anchors)
        b = anchors if best is None else best[0]
    else:
        b = frame_choice.filter_frame(dataset.range, anchors, min_refs=min_refs)
    if say and b != tuple(anchors):
        ids = dataset.node_ids
        own, tri = (frame_choice.frame_reach(dataset.range, t, min_refs) for t in (anchors, b))
        logging.getLogger("jaxcal").info(
            "%s: the filter runs in frame %s, not %s (from it the filter reaches %d of the %d nodes the ranges "
            "fix there; from %s %d of %d)",
            say,
            "/".join(ids[v] for v in b),
            "/".join(ids[v] for v in anchors),
            tri[1],
            tri[0],
            "/".join(ids[v] for v in anchors),
            own[1],
            own[0],
        )
    return b


def _report_frame(dataset: MeshDataset, a, b, final: np.ndarray, method: str) -> tuple[int, int, int]:
    """The frame a run in frame `b` is reported in: the configuration's `a` when the ranges determine it
    and the run placed its a0, a1, a2 (`final`, (N, 2) in `b`), else `b` itself, with one warning line
    (moved into a frame with a mirror image, every node would be placed in one of two frames at random)."""
    from jaxcal.mesh.identify import identify_ranges

    a, b = tuple(a), tuple(b)
    if a == b:
        return a
    own = identify_ranges(dataset.range, a, ids=dataset.node_ids)
    if own.frame_fixed and np.isfinite(final[list(a)]).all():
        return a
    if own.mirror:
        why = f"has a mirror image ({own.mirror})"
    elif not own.frame_fixed:
        why = "is not determined by the ranges"
    else:
        why = "has a node the filter did not localise"
    ids = dataset.node_ids
    logging.getLogger("jaxcal").warning(
        "%s: frame %s %s: the result is in the filter's frame %s",
        method,
        "/".join(ids[v] for v in a),
        why,
        "/".join(ids[v] for v in b),
    )
    return b


def _to_config_frame(final, cov, track, anchors):
    """(final, cov, track) of a proxy-frame run moved into the frame of `anchors` (2-D): each epoch of
    the track through that epoch's estimates of a0, a1, a2, the final position and covariance through
    the final ones (`frame.frame_covariance`, first order)."""
    from jaxcal.mesh.frame import frame_covariance, to_frame_track

    a0, a1, a2 = anchors
    track = to_frame_track(track, a0, a1, a2)
    out = to_frame_track(final[None], a0, a1, a2)[0]
    if np.isfinite(out).all(axis=1).any():
        c = np.where(np.isfinite(cov), cov, 0.0)
        cov = np.where(np.isfinite(out).all(axis=1)[:, None, None], frame_covariance(final, c, a0, a1, a2), np.nan)
    else:
        cov = np.full_like(cov, np.nan)
    return out, cov, track


def software_version() -> str:
    """The `software` attribute of a result: "jaxcal <version>", or "jaxcal" in a source checkout."""
    try:
        from importlib.metadata import version

        return f"jaxcal {version('jaxcal')}"
    except Exception:  # noqa: BLE001 - metadata absent in a source checkout
        return "jaxcal"


def calibrate(dataset: MeshDataset, params=None, config: str | None = None, progress=None) -> Result:
    """`--method pgp`: the grid-based Bayesian filter with hypothesis likelihoods (eq. 3-14); nodes the
    ranges cannot fix in the frame (`identify.py`) are NaN rows, named in one warning line.

    `progress`: optional callback called with the epochs done since its last call."""
    from jaxcal.mesh.masking import mask_result

    res = run_pgp(dataset, params, config, mode="pgp", progress=progress, posterior=False)[0]
    return mask_result(with_pair_covariance(res, dataset.range), dataset.range)


def with_pair_covariance(res: Result, range_m: np.ndarray) -> Result:
    """`res` with each node's covariance replaced by its covariance under per-pair systematic errors sized
    from the data (`pair_covariance.position_covariance`, the unmodelled common range offset as one more shared
    error) at a Cauchy-robust fit of the pair ranges, plus the estimate's displacement from that fit as an
    error shared by the network (`displacement="network"`; gross nodes keep their own displacement too).

    The grid posterior multiplies the likelihoods of every epoch as if the ranges were independent, so it
    narrows with the number of epochs (NEES/dof 3.2 at the median of the development family); a pair's
    offset (antenna delays, static multipath, an NLOS excess) is the same at every epoch and does not average
    out. The grid's own error (its cells, the filter's lag) is in the displacement term, so the grid
    covariance is no longer a floor (the union with it, and each node's own displacement, put the truth
    inside every ellipse by construction: coverage 100 %, NEES/dof 0.65-0.74). Nodes the pairs do not fix
    keep the grid covariance (`masking.mask_result` decides what is reported). Nodes whose mirror image the
    ranges leave undecided get a covariance that spans both images (`mirror.span_undecided`, unless
    `mirror=off`)."""
    from jaxcal.mesh.pair_covariance import position_covariance

    anchors = res.frame_anchors()
    if res.covariance is None or anchors is None or res.position.shape[1] != 2:
        return res
    pc = position_covariance(
        range_m,
        res.position,
        anchors,
        offset=False,
        robust_scale=float(res.params.get("sigma_r", 0.3)),
        displacement="network",
    )
    cov = np.array(res.covariance, dtype=np.float64, copy=True)
    fixed = np.isfinite(pc).all(axis=(1, 2)) & np.isfinite(cov).all(axis=(1, 2))
    cov[fixed] = pc[fixed]
    if res.params.get("mirror", "check") != "off":
        cov = span_undecided(
            range_m, res.ids, anchors, res.position, cov, float(res.params.get("sigma_r", 0.3)), res.method
        )
    return eqx.tree_at(lambda r: r.covariance, res, cov)
