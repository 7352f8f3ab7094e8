"""Node-local grids for large networks (issue #26): the PGP filter at a cost that follows the pairs.

The filter of `pgp` keeps every node's posterior on one square grid around a0, so its memory and
its full-grid epochs grow with the site's area times N (N^2 at constant density), and a site larger
than `extent_m` is cut off. Here every node has grids of its own, placed where its probability is,
on the same lattice of cells (global cell indices, a0 at the centre cell; the lattice itself is never
stored, so the site may be of any size):

- a *wide* grid of L x L cells (`PGPParams.local_m`, by default twice the longest median range plus
  `margin_m` and 1 m: a node lies within radio range of any node it ranged to). A node gets it when it
  first receives ranges from localised neighbours, centred on the most probable cell of the one at the
  shortest range, so the ring of that range lies inside. Until the node is localised its posterior is
  the product of its factors there (the static prior of `pgp`, cell for cell the same values up to
  a constant: the full-grid filter's top_k cells at localisation are the same when they lie inside).
- once localised, each epoch's motion update (eq. 7-8) reads its `top_k` cells and the epoch runs on
  the smallest of three square windows centred on its most probable cell, `window_small_m`,
  `window_m` or the wide L, whose proven bound on the mass outside holds (`fast.outside_bound`, the
  rule of the windowed path of `pgp`, but per node: one node with a wide posterior no longer sends
  every node to the full grid). The wide window's bound fails only when the motion kernel's tail
  reaches L / 2 (never at the defaults); such an epoch is counted in `LocalOut.lost`.

No other approximation: the same hypotheses (eq. 10, from each node's own grid), factors (eq. 11, the
kernel images of `fast.ring_loglik`), normalisation and estimate (eq. 13). Where every node's mass
lies inside its grids this equals the full-grid filter up to rounding (tested against
`pgp.run_filter`); the cost per epoch is about (pairs x window cells), independent of the site's size.
The static prior's normaliser covers the wide grid only, so `log_evidence` before localisation
differs from the full-grid filter's (tuning and sweeps use the full-grid filter).

Used by `pgp.run_pgp` when `grid_mode="local"`, or with `"auto"` (default) when the full grid would
be wider than one wide grid (`use_local`); jacobi order, `likelihood="window"`, mode "pgp", no
snapshots.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxcal.mesh import fast as F
from jaxcal.mesh import grid as G

__all__ = [
    "LocalConfig",
    "LocalState",
    "LocalOut",
    "wide_side",
    "use_local",
    "setup",
    "run_local",
    "region",
    "localised",
    "smooth",
    "scatter",
]


# a node counts as localised (besides hearing `min_refs` localised neighbours) once its posterior holds
# CONC_MASS within `PGPParams.localise_m` of its most probable cell: three rings from nearby nodes can
# leave two mirror modes, and the motion update's top_k cells would lock onto one of them
CONC_MASS = 0.99


class LocalConfig(eqx.Module):
    """Static part (shapes, modes): the lattice, K, H, the three window sides, range model."""

    grid: G.Grid = eqx.field(static=True)  # the lattice: cell size and the index of a0's cell
    top_k: int = eqx.field(static=True)
    n_hyp: int = eqx.field(static=True)
    small: int = eqx.field(static=True)  # window_small_m [cells]; 0: none
    big: int = eqx.field(static=True)  # window_m [cells]
    wide: int = eqx.field(static=True)  # L [cells]
    smoothing: str = eqx.field(static=True)
    median_window: int = eqx.field(static=True)
    range_model: str = eqx.field(static=True)
    localise_m: float = eqx.field(static=True, default=0.0)  # 0: `min_refs` alone


class LocalState(eqx.Module):
    """The scan's carry: per node its grid (the big window or the wide one), and its top_k cells."""

    heard: Bool[Array, "n n"]
    placed: Bool[Array, " n"]  # has a wide grid (received a range from a localised node)
    level: Int[Array, " n"]  # where the posterior is: 0 the big window `fine`, 1 the wide grid `wide`
    fine: Float[Array, "n b b"]
    forg: Int[Array, "n 2"]
    wide: Float[Array, "n l l"]
    worg: Int[Array, "n 2"]
    top_v: Float[Array, "n k"]  # log values of the top_k cells of the posterior (sorted)
    top_i: Int[Array, "n k 2"]  # their lattice indices
    try_small: Bool[Array, " n"]
    conc: Bool[Array, " n"]  # its posterior holds CONC_MASS within CONC_RADIUS_M of its best cell
    smooth: Float[Array, "n 2"]
    started: Bool[Array, " n"]
    buf: Float[Array, "n m 2"]


class LocalOut(eqx.Module):
    """Per-epoch outputs (`pgp.FilterOut`'s fields plus where each node's epoch ran)."""

    estimate: Float[Array, "n 2"]
    raw: Float[Array, "n 2"]
    log_evidence: Float[Array, " n"]
    n_factors: Float[Array, " n"]
    n_wide: Int[Array, ""]  # nodes whose epoch ran on the wide grid
    n_small: Int[Array, ""]  # nodes whose epoch ran on the small window
    lost: Int[Array, ""]  # localised nodes whose wide grid's bound failed (mass may have left it)
    lost_log: Float[Array, ""]  # log of the largest mass those may have dropped (-inf: none)


def wide_side(z: np.ndarray, margin_m: float, cell_m: float, local_m: float = 0.0) -> int:
    """L [cells] (odd): `local_m`, or twice (the longest per-pair median range + margin_m + 1 m)."""
    if local_m <= 0:
        with np.errstate(all="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                med = np.nanmedian(z, axis=0) if z.shape[0] else np.full(z.shape[1:], np.nan)
        longest = float(np.nanmax(med)) if np.isfinite(med).any() else 10.0
        local_m = 2.0 * (longest + margin_m + 1.0)
    return 2 * int(math.ceil(0.5 * local_m / cell_m)) + 1


def use_local(params, n_side_full: int, wide: int, mode: str, snapshots: bool) -> bool:
    """Whether `run_pgp` takes the node-local grids (`PGPParams.grid_mode`)."""
    fits = params.update_order == "jacobi" and params.likelihood == "window" and mode == "pgp" and not snapshots
    if params.grid_mode == "local":
        return fits
    return params.grid_mode == "auto" and fits and n_side_full > wide


def region(kind: Int[Array, ""], org: Int[Array, " 2"], w: int, n_half: int) -> Bool[Array, "w w"]:
    """Allowed cells of a node of `kind` (0 a0, 1 a1, 2 a2, 3 other; `grid.region_masks`) in the
    w x w window at lattice origin `org`."""
    ix = org[0] + jnp.arange(w)[:, None]
    iy = org[1] + jnp.arange(w)[None, :]
    c = n_half
    m0 = (ix == c) & (iy == c)
    m1 = (iy == c) & (ix >= c)
    m2 = jnp.broadcast_to(iy >= c, (w, w))
    return jnp.select([kind == 0, kind == 1, kind == 2], [m0, m1, m2], jnp.ones((w, w), bool))


def setup(params, n: int, z: np.ndarray, allowed: np.ndarray, grid: G.Grid, wide: int):
    """(cfg, kind, log_cells, (nbr, nbr_ok)) for n nodes in filter order; `grid` is the lattice (its
    `n_side` bounds the window origins); `nbr` (N, D) lists each node's possible neighbours (eq. 11
    then costs D, not N, kernel images per node)."""
    big = F.window_side(params.window_m, grid) or grid.n_side
    small = F.window_side(params.window_small_m, grid) if params.window_small_m > 0 else 0
    big = min(big, wide)
    if not (small * small >= params.top_k and small < big):
        small = 0
    cfg = LocalConfig(
        grid=grid,
        top_k=params.top_k,
        n_hyp=min(params.max_hyp, params.top_k),
        small=small,
        big=big,
        wide=wide,
        smoothing=params.smoothing,
        median_window=params.median_window,
        range_model=params.range_model,
        localise_m=float(params.localise_m),
    )
    kind = np.minimum(np.arange(n), 3).astype(np.int32)
    # each node's neighbours that can ever give it a factor (allowed, a range in some epoch), padded
    can = np.asarray(allowed) & np.isfinite(z).any(axis=0)
    deg = max(int(can.sum(axis=1).max()), 1)
    nbr = np.zeros((n, deg), np.int32)
    nbr_ok = np.zeros((n, deg), bool)
    for i in range(n):
        js = np.flatnonzero(can[i])
        nbr[i, : js.size] = js
        nbr_ok[i, : js.size] = True
    # log of each node's number of allowed cells on the lattice (bounds the mass outside a window)
    ns, c = grid.n_side, grid.n_half
    cells = np.array([1.0, ns - c, ns * (ns - c)] + [float(ns * ns)] * max(n - 3, 0))[:n]
    return cfg, jnp.asarray(kind), jnp.asarray(np.log(cells)), (jnp.asarray(nbr), jnp.asarray(nbr_ok))


def init_state(cfg: LocalConfig, n: int, dtype) -> LocalState:
    """Before the first epoch: a0 placed on its cell (localised from the start), the others unplaced."""
    c = cfg.grid.n_half
    b, w = cfg.big, cfg.wide
    k = cfg.top_k
    top_v = jnp.full((n, k), -jnp.inf, dtype).at[0, 0].set(0.0)
    top_i = jnp.full((n, k, 2), c, jnp.int32)
    org0 = jnp.full((n, 2), c - w // 2, jnp.int32)
    return LocalState(
        heard=jnp.zeros((n, n), bool),
        placed=jnp.zeros((n,), bool).at[0].set(True),
        level=jnp.ones((n,), jnp.int32),
        fine=jnp.full((n, b, b), -jnp.inf, dtype),
        forg=jnp.zeros((n, 2), jnp.int32),
        wide=jnp.full((n, w, w), -jnp.inf, dtype).at[0, w // 2, w // 2].set(0.0),
        worg=org0,
        top_v=top_v,
        top_i=top_i,
        try_small=jnp.ones((n,), bool),
        conc=jnp.full((n,), cfg.localise_m <= 0).at[0].set(True),
        smooth=jnp.full((n, 2), jnp.nan, dtype),
        started=jnp.zeros((n,), bool),
        buf=jnp.full((n, cfg.median_window, 2), jnp.nan, dtype),
    )


def _top(cfg: LocalConfig, post: Float[Array, "w w"], org: Int[Array, " 2"]):
    """(values, lattice indices) of the top_k cells of a window's log posterior."""
    w = post.shape[0]
    vals, idx = G.top_k(post.reshape(-1), cfg.top_k)
    return vals, org[None, :] + jnp.stack([idx // w, idx % w], axis=-1).astype(jnp.int32)


def _positions(cfg: LocalConfig, idx: Int[Array, "... 2"], dtype) -> Float[Array, "... 2"]:
    return (idx - cfg.grid.n_half).astype(dtype) * cfg.grid.cell_m


def _loglik(cfg, prm, org, w, hyps, z_i, use_i, nlos):
    """Eq. (11) on the w x w window at `org`: kernel images, else the direct evaluation.

    On the windows of a localised node (w < L) every possible neighbour is evaluated at once and
    the unused ones masked (small images, vectorised); on the wide grid a loop over the neighbours
    skips those without a range (before localisation only a few are used), pair by pair as
    `fast.ring_loglik_grid`."""
    dtype = hyps[1].dtype
    if w < cfg.wide:
        ll, ok = F.ring_loglik(org, w, cfg.grid, hyps[0], hyps[1], hyps[2], z_i, use_i, prm.p_out, nlos)

        def direct():
            cells = F.window_cells(org, cfg.grid, w, dtype)
            return G.node_loglik(cells, hyps[0], hyps[1], hyps[2], z_i, use_i, prm.p_out, nlos)

        return jax.lax.cond(ok, lambda: ll, direct)
    return F.ring_loglik_loop(org, w, cfg.grid, hyps[0], hyps[1], hyps[2], z_i, use_i, prm.p_out, nlos)


def _node(cfg: LocalConfig, prm, hyps, step_m, nlos, x):
    """One node's epoch (see the module docstring). Returns the node's new
    (placed, level, fine, forg, wide, worg, top_v, top_i, try_small, raw, ev, ran, conc, dropped) with
    `ran` 0 none, 1 small, 2 big, 3 wide, 4 wide with its bound failed, `dropped` then the log of its
    bound on the mass outside (else -inf)."""
    kind, placed, loc, level, fine, forg, wide, worg, top_v, top_i, try_small, conc = x[:12]
    z_i, use_i, centre, log_cells, nb = x[12:]
    hyps = tuple(h[nb] for h in hyps)  # the node's possible neighbours only
    dtype = fine.dtype
    none = jnp.asarray(-jnp.inf, dtype)
    ns, n_half = cfg.grid.n_side, cfg.grid.n_half
    nan2 = jnp.full((2,), jnp.nan, dtype)
    b, w_l = cfg.big, cfg.wide
    any_use = jnp.any(use_i)

    def keep():
        return (
            placed,
            level,
            fine,
            forg,
            wide,
            worg,
            top_v,
            top_i,
            try_small,
            nan2,
            jnp.zeros((), dtype),
            _i(0),
            conc,
            none,
        )

    def static():  # not localised: the product of its factors on the wide grid
        org = jnp.where(placed, worg, F.window_origin(centre[0] * ns + centre[1], ns, w_l))
        m = region(kind, org, w_l, n_half)
        prior = jnp.where(m, jnp.where(placed, wide, 0.0), -jnp.inf)
        ll = _loglik(cfg, prm, org, w_l, hyps, z_i, use_i, nlos).reshape(w_l, w_l)
        post = jnp.where(m, prior + ll, -jnp.inf)
        lse = jax.nn.logsumexp(post)
        ev = lse - jax.nn.logsumexp(prior)
        post = post - lse
        tv, ti = _top(cfg, post, org)
        raw = _estimate(cfg, prm, post, org)
        cells = F.window_cells(org, cfg.grid, w_l, dtype)
        near = jnp.sum(jnp.square(cells - _positions(cfg, ti[0], dtype)), axis=-1) <= cfg.localise_m**2
        held = jnp.sum(jnp.where(near, jnp.exp(post.reshape(-1)), 0.0)) >= CONC_MASS
        held = held | (cfg.localise_m <= 0)
        return (jnp.asarray(True), _i(1), fine, forg, post, org, tv, ti, try_small, raw, ev, _i(3), held, none)

    def moving():  # localised: eq. (7)-(8) from its top_k cells onto a window around the best one
        src = _positions(cfg, top_i, dtype)
        flat = top_i[0, 0] * ns + top_i[0, 1]

        def run(w):
            org = F.window_origin(flat, ns, w)
            cells = F.window_cells(org, cfg.grid, w, dtype)
            prior = F.predict_window(top_v, src, cells, step_m, prm.sigma_v)
            m = region(kind, org, w, n_half).reshape(-1)
            ll = _loglik(cfg, prm, org, w, hyps, z_i, use_i, nlos)
            post = jnp.where(m, prior + ll, -jnp.inf)
            lse = jax.nn.logsumexp(post)
            ev = lse - jax.nn.logsumexp(jnp.where(m, prior, -jnp.inf))
            kw = dict(n_side=ns, cell_m=cfg.grid.cell_m, step_m=step_m, sigma_v=prm.sigma_v)
            pb = F.outside_bound(top_v, top_i, org, w=w, **kw) - lse
            post = (post - lse).reshape(w, w)
            if cfg.small and w >= b:  # would the small window have held? (lse here >= its lse)
                o_s = F.window_origin(flat, ns, cfg.small)
                sb = F.outside_bound(top_v, top_i, o_s, w=cfg.small, **kw) - lse
                nxt = sb + log_cells < F.WINDOW_LOG_TOL - F.SMALL_WINDOW_MARGIN
            else:
                nxt = pb + log_cells < F.WINDOW_LOG_TOL - F.SMALL_WINDOW_MARGIN
            if w == w_l:  # the wide grid: hand its bound on the mass outside through
                nxt = pb + log_cells
            return post, org, ev, pb + log_cells < F.WINDOW_LOG_TOL, nxt

        def as_fine(post, org, ev, nxt, ran):
            out = post
            if post.shape[0] < b:  # the small window inside the big one centred on the same cell
                o_b = F.window_origin(flat, ns, b)
                out = jax.lax.dynamic_update_slice(jnp.full((b, b), -jnp.inf, dtype), post, tuple(org - o_b))
                org = o_b
            tv, ti = _top(cfg, out, org)
            raw = _estimate(cfg, prm, out, org)
            return (placed, _i(0), out, org, wide, worg, tv, ti, nxt, raw, ev, _i(ran), conc, none)

        def wide_run():
            post, org, ev, held, outb = run(w_l)
            tv, ti = _top(cfg, post, org)
            raw = _estimate(cfg, prm, post, org)
            ran = jnp.where(held, _i(3), _i(4))
            dropped = jnp.where(held, -jnp.inf, outb)
            return (placed, _i(1), fine, forg, post, org, tv, ti, jnp.asarray(False), raw, ev, ran, conc, dropped)

        def big_run():
            post, org, ev, held, nxt = run(b)
            return jax.lax.cond(held, lambda: as_fine(post, org, ev, nxt, 2), wide_run)

        if not cfg.small:
            return big_run()

        def small_run():
            post, org, ev, held, nxt = run(cfg.small)
            return jax.lax.cond(held, lambda: as_fine(post, org, ev, nxt, 1), big_run)

        return jax.lax.cond(try_small, small_run, big_run)

    def active():
        return jax.lax.cond(loc, moving, static)

    return jax.lax.cond(loc | any_use, active, keep)


def _i(v) -> Int[Array, ""]:
    return jnp.asarray(v, jnp.int32)


def _estimate(cfg, prm, post, org):
    cells = F.window_cells(org, cfg.grid, post.shape[0], post.dtype)
    return G.window_estimate(post.reshape(-1), cells, prm.r_est)


def localised(heard: Bool[Array, "n n"], need: Float[Array, " n"]) -> Bool[Array, " n"]:
    """Nodes that have received ranges from at least `need` distinct localised neighbours."""
    return jnp.sum(heard, axis=1) >= need


def smooth(cfg, prm, st, raw, loc):
    """Eq. (14) for nodes with an estimate this epoch; returns (estimate, smooth, started, buf).

    `cfg`: `smoothing`, `median_window`; `prm.alpha`; `st`: `smooth`, `started`, `buf` (the filter
    states of `pgp` and of this module alike)."""
    if cfg.smoothing == "none":
        return raw, st.smooth, st.started, st.buf
    buf = st.buf
    target = raw
    if cfg.smoothing == "median-ema":
        pushed = jnp.concatenate([buf[:, 1:], raw[:, None, :]], axis=1)
        buf = jnp.where(loc[:, None, None], pushed, buf)
        target = jnp.nanmedian(buf, axis=1)
    ema = jnp.where(st.started[:, None], prm.alpha * target + (1 - prm.alpha) * st.smooth, target)
    sm = jnp.where(loc[:, None], ema, st.smooth)
    started = st.started | loc
    return sm, sm, started, buf


def _epoch(cfg: LocalConfig, prm, allowed, need, kind, log_cells, nbrs, st: LocalState, x):
    z, dt, valid = x
    n = st.heard.shape[0]
    dtype = st.fine.dtype
    step_m = prm.v * dt
    nlos = (prm.nlos_weight, prm.nlos_mean_m) if cfg.range_model == "mixture" else None
    nbr, nbr_ok = nbrs
    loc = localised(st.heard, need) & st.conc
    use = allowed & jnp.isfinite(z) & loc[None, :] & valid
    # eq. (10) from each node's own top cells (the first n_hyp of its top_k, same order)
    hv = st.top_v[:, : cfg.n_hyp]
    before = jnp.concatenate([jnp.zeros((n, 1), dtype), jnp.cumsum(jnp.exp(hv), axis=1)[:, :-1]], axis=1)
    keep = ((before < prm.tau) & jnp.isfinite(hv)).at[:, 0].set(True)
    lw = jnp.where(keep, hv, -jnp.inf)
    lw = lw - jax.nn.logsumexp(lw, axis=1, keepdims=True)
    hyps = (_positions(cfg, st.top_i[:, : cfg.n_hyp], dtype), lw, jnp.broadcast_to(prm.sigma_r, (n,)))
    # where a node's wide grid goes when it is placed: on the best cell of its nearest used neighbour
    nearest = jnp.argmin(jnp.where(use, z, jnp.inf), axis=1)
    centre = st.top_i[nearest, 0]
    xs = (
        kind,
        st.placed,
        loc & valid,
        st.level,
        st.fine,
        st.forg,
        st.wide,
        st.worg,
        st.top_v,
        st.top_i,
        st.try_small,
        st.conc,
        jnp.take_along_axis(jnp.where(use, z, 0.0), nbr, axis=1),
        jnp.take_along_axis(use, nbr, axis=1) & nbr_ok,
        centre,
        log_cells,
        nbr,
    )
    placed, level, fine, forg, wide, worg, top_v, top_i, try_small, raw, ev, ran, conc, dropped = jax.lax.map(
        lambda a: _node(cfg, prm, hyps, step_m, nlos, a), xs
    )
    lost = ran == 4
    heard = st.heard | use
    loc_new = localised(heard, need) & conc
    raw = jnp.where(loc_new[:, None], raw, jnp.nan)
    new = dataclasses.replace(
        st,
        heard=heard,
        placed=placed,
        level=level,
        fine=fine,
        forg=forg,
        wide=wide,
        worg=worg,
        top_v=top_v,
        top_i=top_i,
        try_small=try_small,
        conc=conc,
    )
    est, sm, started, buf = smooth(cfg, prm, st, raw, loc_new)
    est = jnp.where(loc_new[:, None], est, jnp.nan)
    new = dataclasses.replace(new, smooth=sm, started=started, buf=buf)
    new = jax.tree.map(lambda a, b: jnp.where(valid, a, b), new, st)
    out = LocalOut(
        est,
        raw,
        ev,
        jnp.sum(use, axis=1).astype(dtype),
        jnp.sum(ran >= 3),
        jnp.sum(ran == 1),
        jnp.sum(lost),
        jnp.max(dropped),
    )
    return new, out


@eqx.filter_jit
def _scan(cfg, prm, allowed, need, kind, log_cells, nbrs, st, z, dt, valid):
    return jax.lax.scan(lambda s, x: _epoch(cfg, prm, allowed, need, kind, log_cells, nbrs, s, x), st, (z, dt, valid))


@eqx.filter_jit
def _final(cfg: LocalConfig, st: LocalState):
    """(N, 2, 2) covariance of each node's final posterior (`grid.mean_cov` on its own grid)."""

    def one(level, fine, forg, wide, worg):
        def cov(post, org):
            cells = F.window_cells(org, cfg.grid, post.shape[0], post.dtype)
            return G.mean_cov(post.reshape(-1), cells)[1]

        return jnp.where(level == 0, cov(fine, forg), cov(wide, worg))

    return jax.vmap(one)(st.level, st.fine, st.forg, st.wide, st.worg)


def run_local(cfg: LocalConfig, prm, allowed, need, kind, log_cells, nbrs, z, dt, chunk: int = 25, progress=None):
    """All epochs from the start, in chunks of `chunk` epochs (one compilation; `progress(epochs)`
    after each). Returns (final LocalState, LocalOut of every epoch, (N, 2, 2) final covariance)."""
    n = z.shape[1]
    dtype = jnp.result_type(float)
    st = init_state(cfg, n, dtype)
    z = jnp.asarray(z, dtype)
    dt = jnp.asarray(dt, dtype)
    k_all = z.shape[0]
    outs = []
    for k in range(0, k_all, chunk):
        m = min(chunk, k_all - k)
        zc, dc = z[k : k + m], dt[k : k + m]
        if m < chunk:
            zc = jnp.concatenate([zc, jnp.full((chunk - m,) + zc.shape[1:], jnp.nan, dtype)])
            dc = jnp.concatenate([dc, jnp.zeros((chunk - m,), dtype)])
        st, out = _scan(cfg, prm, allowed, need, kind, log_cells, nbrs, st, zc, dc, jnp.arange(chunk) < m)
        outs.append(jax.tree.map(lambda a, m=m: a[:m], out))
        if progress is not None:
            progress(m)
    out = jax.tree.map(lambda *a: jnp.concatenate(a), *outs)
    return st, out, _final(cfg, st)


def scatter(cfg: LocalConfig, st: LocalState) -> np.ndarray:
    """(N, n, n) posterior probabilities on the lattice (each node's grid placed, 0 elsewhere): for
    inspection only, memory N n^2."""
    n, ns = st.level.shape[0], cfg.grid.n_side
    out = np.zeros((n, ns, ns))
    level = np.asarray(st.level)
    for i in range(n):
        post, org = (st.fine[i], st.forg[i]) if level[i] == 0 else (st.wide[i], st.worg[i])
        p = np.exp(np.asarray(post, dtype=np.float64))
        o = np.asarray(org)
        out[i, o[0] : o[0] + p.shape[0], o[1] : o[1] + p.shape[1]] = p
    return out
