"""The filter's epoch scans and their drivers: the public filter API that tuning, sweeps, the
lockstep batch and the checkpointed segments build on.

- `scan`: `lax.scan` of epochs from a state (traceable: inside jit, vmap, grad, checkpoint);
  `run_scan` is it jitted.
- `scan_windows`: windowed epochs only, no full grid in the carry (the fast path's chunks).
- `filter_epochs`: the whole filter from the initial posteriors; `run_filter` is it jitted.
- `run_chunked` / `advance_chunked`: the fast path driven from the host in chunks; `run_segmented`:
  one scan in host segments (progress callbacks). All give the epochs of `run_filter`.

Shapes: `nodes` in filter order (a0, a1, a2, others), `epochs` of `inputs.z`, `(nx, ny)` the grid.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxcal.mesh import fast as F
from jaxcal.mesh import grid as G
from jaxcal.mesh import local as L
from jaxcal.mesh.pgp.kernels import WindowStep, hypotheses, node_update, remat, skipped_window_step, windows_epoch
from jaxcal.mesh.pgp.state import (
    FilterConfig,
    FilterInputs,
    FilterOut,
    FilterParams,
    FilterState,
    full_logpost,
    full_state,
    init_state,
)

__all__ = [
    "scan",
    "run_scan",
    "scan_windows",
    "filter_epochs",
    "run_filter",
    "run_chunked",
    "advance_chunked",
    "run_segmented",
]


class EpochUpdate(eqx.Module):
    """One epoch's new posteriors and the outputs the scan reports (`scan`'s two branches: the
    full grid, or a held `WindowStep`).

    Attributes:
        logpost: (nodes, nx, ny) full-grid log posteriors (stale while the windows hold).
        heard: (nodes, nodes) which neighbours each node has received ranges from (localised then).
        log_evidence, n_factors, raw, log_mass: the epoch's `FilterOut` fields of these names.
        window, origin, bound, row: the windowed representation (`FilterState`'s `win`, `org`,
            `bound`, `row`).
    """

    logpost: Float[Array, "nodes nx ny"]
    heard: Bool[Array, "nodes nodes"]
    log_evidence: Float[Array, " nodes"]
    n_factors: Float[Array, " nodes"]
    raw: Float[Array, "nodes 2"]
    window: Float[Array, "nodes w w"]
    origin: Int[Array, "nodes 2"]
    bound: Float[Array, " nodes"]
    row: Float[Array, " n"]
    log_mass: Float[Array, " nodes"]


def _log_cells(inputs: FilterInputs, dtype) -> Float[Array, " nodes"]:
    """Log of each node's number of allowed cells: bounds the mass outside its window."""
    mask = inputs.mask.reshape(inputs.mask.shape[0], -1)
    return jnp.log(jnp.maximum(jnp.sum(mask, axis=1), 1).astype(dtype))


def _window_ready(inputs: FilterInputs, state: FilterState, z, log_cells):
    """(ranges used, whether the epoch may run on the windows): every node localised and every
    window's bound below `fast.WINDOW_LOG_TOL`."""
    loc = L.localised(state.heard, inputs.need)
    use = inputs.allowed & jnp.isfinite(z) & loc[None, :]
    return use, jnp.all(loc) & jnp.all(state.bound + log_cells < F.WINDOW_LOG_TOL)


def _window_log_mass(step: WindowStep) -> Float[Array, " nodes"]:
    n = step.window.shape[0]
    return jax.nn.logsumexp(step.window.reshape(n, -1), axis=1).at[1].set(jax.nn.logsumexp(step.row))


def _estimates(config: FilterConfig, params: FilterParams, inputs: FilterInputs, state: FilterState, heard, raw):
    """The epoch's bookkeeping after the update: eq. (13) estimates kept for localised nodes only,
    eq. (14) smoothing. Returns (estimate, raw, smooth, started, buf)."""
    nan2 = jnp.full(raw.shape, jnp.nan, raw.dtype)
    loc = L.localised(heard, inputs.need)
    raw = jnp.where(loc[:, None], raw, nan2)
    est, smooth, started, buf = L.smooth(config, params, state, raw, loc)
    est = jnp.where(loc[:, None], est, nan2)
    return est, raw, smooth, started, buf


def scan(
    config: FilterConfig,
    params: FilterParams,
    inputs: FilterInputs,
    state: FilterState,
    first_epoch=0,
) -> tuple[FilterState, FilterOut]:
    """`lax.scan` of the epochs of `inputs.z` (epochs, nodes, nodes) from `state`.

    Traceable (jit, vmap, grad, `jax.checkpoint`); `run_scan` is it jitted. Two calls on
    consecutive epoch ranges, the second from the first's state, equal one call over both.

    Args:
        config, params, inputs: as `prepare` returns them; only `inputs.z` and `inputs.dt` are per
            epoch.
        state: the state before the first epoch (`init_state`, or a previous scan's; may be
            windowed, see `full_logpost`).
        first_epoch: index of the first epoch in the recording (matched against snapshot epochs).

    Returns:
        (state after the last epoch, possibly windowed; FilterOut with a leading epochs axis).
    """
    cfg, prm, inp, st0 = config, params, inputs, state
    n = st0.logpost.shape[0]
    dtype = st0.logpost.dtype
    cells = cfg.grid.cells(dtype)
    c = cells.shape[0]
    mask = inp.mask.reshape(n, c)
    windowed_mode = cfg.window > 0 and cfg.update_order == "jacobi"
    log_cells = _log_cells(inp, dtype)

    def upd(lp, loc, hyps, z, use, step_m):
        args = (lp, mask, loc, z, use)
        if cfg.likelihood != "dense":  # lax.map: a vmapped cond would evaluate the skipped work too
            return jax.lax.map(
                lambda a: node_update(cfg, prm, cells, a[0], a[1], a[2], hyps, a[3], a[4], step_m),
                args,
            )
        return jax.vmap(lambda *a: node_update(cfg, prm, cells, a[0], a[1], a[2], hyps, a[3], a[4], step_m))(*args)

    def full_epoch(st: FilterState, z, step_m) -> EpochUpdate:
        """The direct evaluation on every cell; re-centres the windows when there are any."""
        lp = full_logpost(cfg, st).reshape(n, c)
        heard = st.heard
        if cfg.update_order == "jacobi":
            loc = L.localised(heard, inp.need)
            use = inp.allowed & jnp.isfinite(z) & loc[None, :]
            hyps = hypotheses(cfg, prm, lp, cells)
            lp, ev = upd(lp, loc, hyps, z, use, step_m)
            heard = heard | use
            nf = jnp.sum(use, axis=1).astype(dtype)
        else:
            hyps = hypotheses(cfg, prm, lp, cells)

            def one(carry, i):
                lp, heard, hyps = carry
                loc = L.localised(heard, inp.need)
                use_i = inp.allowed[i] & jnp.isfinite(z[i]) & loc
                new, ev_i = node_update(cfg, prm, cells, lp[i], mask[i], loc[i], hyps, z[i], use_i, step_m)
                lp = lp.at[i].set(new)
                heard = heard.at[i].set(heard[i] | use_i)
                h1 = hypotheses(cfg, prm, new[None], cells)
                hyps = tuple(h.at[i].set(h1_[0]) for h, h1_ in zip(hyps, h1, strict=True))
                return (lp, heard, hyps), (ev_i, jnp.sum(use_i).astype(dtype))

            (lp, heard, _), (ev, nf) = jax.lax.scan(one, (lp, heard, hyps), jnp.arange(n))
        raw = jax.vmap(G.window_estimate, in_axes=(0, None, None))(lp, cells, prm.r_est)
        logpost = lp.reshape(st.logpost.shape)
        if windowed_mode:
            win, org, bound = jax.vmap(F.extract_window, in_axes=(0, None))(logpost, cfg.window)
            row = logpost[1, :, cfg.grid.n_half]
            bound = bound.at[1].set(-jnp.inf)  # a1 is kept as its whole row
        else:
            win, org, bound, row = st.win, st.org, st.bound, st.row
        lm = jax.nn.logsumexp(lp, axis=1)
        return EpochUpdate(logpost, heard, ev, nf, raw, win, org, bound, row, lm)

    def epoch(st: FilterState, x):
        z, dt, k = x
        step_m = prm.v * dt
        if windowed_mode:
            use0, pre = _window_ready(inp, st, z, log_cells)
            step = jax.lax.cond(
                pre,
                remat(cfg, lambda: windows_epoch(cfg, prm, inp, st, z, step_m, use0, log_cells)),
                lambda: skipped_window_step(st),
            )
            ok = pre & step.held
            # after a full-grid epoch the windows are re-centred: try the small one first again
            small_next = jnp.where(ok, step.small_next, True)
            ran_small = ok & step.ran_small

            # the full grid is an explicit operand (not a closure constant) of both branches, so
            # the windowed branch can hand it through without a copy
            def take_window(lp_full):
                nf = jnp.sum(use0, axis=1).astype(dtype)
                return EpochUpdate(
                    logpost=lp_full,
                    heard=st.heard | use0,
                    log_evidence=step.log_evidence,
                    n_factors=nf,
                    raw=step.raw,
                    window=step.window,
                    origin=step.origin,
                    bound=step.bound,
                    row=step.row,
                    log_mass=_window_log_mass(step),
                )

            def take_full(lp_full):
                return full_epoch(dataclasses.replace(st, logpost=lp_full), z, step_m)

            upd_ = jax.lax.cond(ok, take_window, remat(cfg, take_full), st.logpost)
            windowed = ok
        else:
            upd_ = full_epoch(st, z, step_m)
            windowed = st.windowed
            small_next, ran_small = st.small, jnp.asarray(False)
        est, raw, smooth, started, buf = _estimates(cfg, prm, inp, st, upd_.heard, upd_.raw)
        new = FilterState(
            logpost=upd_.logpost,
            heard=upd_.heard,
            smooth=smooth,
            started=started,
            buf=buf,
            snaps=st.snaps,
            win=upd_.window,
            org=upd_.origin,
            bound=upd_.bound,
            windowed=windowed,
            row=upd_.row,
            small=small_next,
        )
        if cfg.n_snap:
            hit = inp.snap_at == k
            snaps = jax.lax.cond(
                jnp.any(hit),
                lambda: jnp.where(hit[:, None, None, None], full_logpost(cfg, new)[None], st.snaps),
                lambda: st.snaps,
            )
            new = dataclasses.replace(new, snaps=snaps)
        return new, FilterOut(est, raw, upd_.log_mass, upd_.log_evidence, upd_.n_factors, windowed, ran_small)

    k = inp.z.shape[0]
    body = jax.checkpoint(epoch) if cfg.remat else epoch
    return jax.lax.scan(body, st0, (inp.z, inp.dt, first_epoch + jnp.arange(k)))


def filter_epochs(
    config: FilterConfig,
    params: FilterParams,
    inputs: FilterInputs,
    logpost0: Float[Array, "nodes nx ny"],
) -> tuple[FilterState, FilterOut]:
    """The recursive filter over every epoch of `inputs` from the initial (nodes, nx, ny) log
    posteriors `logpost0` (`prepare`'s): `scan` from `init_state`. Traceable; `run_filter` is it
    jitted.

    Returns:
        (final FilterState, its `logpost` the full-grid posteriors (windows placed on the grid);
        FilterOut with a leading epochs axis).
    """
    state, out = scan(config, params, inputs, init_state(config, logpost0))
    return full_state(config, state), out


run_filter = eqx.filter_jit(filter_epochs)
"""`filter_epochs` jitted (`eqx.filter_jit`): (config, params, inputs, logpost0) -> (final FilterState,
per-epoch FilterOut); tuning and sweeps call it (also inside their own vmap / jit)."""
run_scan = eqx.filter_jit(scan)
"""`scan` jitted (`eqx.filter_jit`): (config, params, inputs, state, first_epoch) -> (FilterState,
FilterOut); pass `first_epoch` as an array so that chunks at other epochs do not recompile."""


def scan_windows(
    config: FilterConfig,
    params: FilterParams,
    inputs: FilterInputs,
    state: FilterState,
    valid: Bool[Array, " epochs"],
    first_epoch,
) -> tuple[FilterState, FilterOut, Int[Array, ""]]:
    """Windowed epochs only, without the full grid in the carry (its copies cost O(cells) per epoch).

    Stops (state frozen) at the first epoch that is not `valid` or cannot run on the windows; the
    epochs it ran equal `scan`'s. Traceable (the lockstep batch vmaps it). `state.logpost` is not
    read (pass a small placeholder and put the full grid back afterwards).

    Args:
        config, params, inputs: as for `scan` (`config.window` > 0, jacobi order).
        state: a state whose windows hold (every node localised, bounds below the tolerance).
        valid: (epochs,) which epochs of `inputs.z` to run (a padded chunk: False at the padding).
        first_epoch: index of the first epoch in the recording.

    Returns:
        (state after the last epoch run, FilterOut of every epoch of `inputs.z` (rows past the stop
        are not epochs of the filter), number of epochs run).
    """
    cfg, prm, inp = config, params, inputs
    dtype = state.win.dtype
    log_cells = _log_cells(inp, dtype)

    def epoch(carry, x):
        st, go = carry
        z, dt, k, v = x
        step_m = prm.v * dt
        use0, pre = _window_ready(inp, st, z, log_cells)
        step = jax.lax.cond(
            go & v & pre,
            lambda: windows_epoch(cfg, prm, inp, st, z, step_m, use0, log_cells),
            lambda: skipped_window_step(st),
        )
        go = go & v & pre & step.held
        heard = st.heard | use0
        est, raw, smooth, started, buf = _estimates(cfg, prm, inp, st, heard, step.raw)
        lm = _window_log_mass(step)
        new = dataclasses.replace(
            st,
            heard=heard,
            smooth=smooth,
            started=started,
            buf=buf,
            win=step.window,
            org=step.origin,
            bound=step.bound,
            row=step.row,
            windowed=jnp.asarray(True),
            small=step.small_next,
        )
        new = jax.tree.map(lambda a, b: jnp.where(go, a, b), new, st)
        nf = jnp.sum(use0, axis=1).astype(dtype)
        return (new, go), (FilterOut(est, raw, lm, step.log_evidence, nf, go, go & step.ran_small), go)

    k = inp.z.shape[0]
    (st, _), (out, done) = jax.lax.scan(
        epoch, (state, jnp.asarray(True)), (inp.z, inp.dt, first_epoch + jnp.arange(k), valid)
    )
    return st, out, jnp.sum(done)


_run_scan_windows = eqx.filter_jit(scan_windows)


def run_chunked(
    config: FilterConfig,
    params: FilterParams,
    inputs: FilterInputs,
    logpost0: Float[Array, "nodes nx ny"],
    chunk: int = 64,
    full_chunk: int = 4,
    progress: Callable[[int], object] | None = None,
) -> tuple[FilterState, FilterOut]:
    """`run_filter` for `likelihood="window"` driven from the host in chunks of epochs.

    Same epochs, same results as `run_filter`; while the windows hold, chunks of `chunk` epochs
    run without the full grid in the scan's carry (`scan_windows`); other epochs run in chunks of
    `full_chunk` with the full grid (`scan`). Each chunk length compiles once.

    Args:
        progress: optional callback, called with the number of epochs done since its last call
            (after every chunk). Without the fast path (other likelihoods, snapshots) the one
            scan then runs in segments (`run_segmented`); results are identical either way.

    Returns:
        (final FilterState with the full-grid `logpost`, FilterOut of all epochs).
    """
    if not config.window or config.n_snap:
        if progress is not None:
            return run_segmented(config, params, inputs, logpost0, progress=progress)
        return run_filter(config, params, inputs, logpost0)
    st, out = advance_chunked(
        config, params, inputs, init_state(config, logpost0), 0, None, chunk, full_chunk, progress
    )
    return full_state(config, st), out


def advance_chunked(
    config: FilterConfig,
    params: FilterParams,
    inputs: FilterInputs,
    state: FilterState,
    start: int = 0,
    stop: int | None = None,
    chunk: int = 64,
    full_chunk: int = 4,
    progress: Callable[[int], object] | None = None,
) -> tuple[FilterState, FilterOut]:
    """Epochs `start:stop` of `inputs` from `state` on `run_chunked`'s fast path (which is this
    from `init_state` over all epochs, then `full_state`).

    The returned state is the scan's own (possibly windowed: `logpost` stale), so a later call
    with `start=stop` continues exactly where this one ended: two calls give the epochs and the
    state of one (tested). Needs `config.window` and no snapshots.

    Returns:
        (state after epoch `stop - 1`, FilterOut of epochs `start:stop`).
    """
    if not config.window or config.n_snap:
        raise ValueError("advance_chunked: needs the windowed likelihood and no snapshots")
    st = state
    n_ep = int(inputs.z.shape[0]) if stop is None else int(stop)
    n = st.logpost.shape[0]
    log_cells = np.log(np.maximum(np.asarray(inputs.mask).reshape(n, -1).sum(1), 1))
    outs, k = [], int(start)

    def part(a, b, pad=0):
        z, dt = inputs.z[a:b], inputs.dt[a:b]
        if pad:
            z = jnp.concatenate([z, jnp.full((pad,) + z.shape[1:], jnp.nan, z.dtype)])
            dt = jnp.concatenate([dt, jnp.zeros((pad,), dt.dtype)])
        return dataclasses.replace(inputs, z=z, dt=dt)

    while k < n_ep:
        loc = np.asarray(L.localised(st.heard, inputs.need))
        if loc.all() and np.all(np.asarray(st.bound) + log_cells < F.WINDOW_LOG_TOL):
            m = min(chunk, n_ep - k)
            valid = jnp.arange(chunk) < m
            full = st.logpost
            small = dataclasses.replace(st, logpost=jnp.zeros((n, 1, 1), full.dtype))
            st2, out, ran = _run_scan_windows(config, params, part(k, k + m, chunk - m), small, valid, jnp.asarray(k))
            done = int(ran)
            if done:
                st = dataclasses.replace(st2, logpost=full)
                outs.append(jax.tree.map(lambda a, d=done: a[:d], out))
                k += done
                if progress is not None:
                    progress(done)
            if done == m:
                continue
        m = full_chunk if n_ep - k >= full_chunk else 1
        st, out = run_scan(config, params, part(k, k + m), st, jnp.asarray(k))
        outs.append(out)
        k += m
        if progress is not None:
            progress(m)
    if not outs:
        raise ValueError(f"advance_chunked: no epochs in {start}:{n_ep}")
    return st, jax.tree.map(lambda *a: jnp.concatenate(a), *outs)


def run_segmented(
    config: FilterConfig,
    params: FilterParams,
    inputs: FilterInputs,
    logpost0: Float[Array, "nodes nx ny"],
    segment: int = 64,
    progress: Callable[[int], object] | None = None,
) -> tuple[FilterState, FilterOut]:
    """`run_filter` as a host loop over segments of `segment` epochs (one jitted `scan` per
    segment, the state carried from one call to the next), calling `progress(epochs)` after each.

    The same scan body on the same state: results are bit-for-bit those of `run_filter`
    (tested). Segments of one length compile once (plus once for a shorter last segment).

    Returns:
        (final FilterState with the full-grid `logpost`, FilterOut of all epochs).
    """
    n_ep = int(inputs.z.shape[0])
    st = init_state(config, logpost0)
    outs = []
    for k in range(0, n_ep, segment):
        m = min(segment, n_ep - k)
        part = dataclasses.replace(inputs, z=inputs.z[k : k + m], dt=inputs.dt[k : k + m])
        st, out = run_scan(config, params, part, st, jnp.asarray(k))
        outs.append(out)
        if progress is not None:
            progress(m)
    out = jax.tree.map(lambda *a: jnp.concatenate(a), *outs)
    return full_state(config, st), out
