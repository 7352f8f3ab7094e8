"""A batch of PGP runs on the windowed fast path, vmapped: `pgp.run_chunked` for B runs at once.

Under `jax.vmap` a `lax.cond` whose predicate differs between runs evaluates both branches, so one
vmapped `pgp.filter_epochs` pays the full-grid epoch at every epoch of every run. Here the host decides
the branch for the whole batch, per step, as `run_chunked` does for one run: the runs whose windows
hold advance by a vmapped window-only chunk (`pgp.scan_windows`, no full grid in the carry; each
run stops at its own first epoch that cannot run windowed), and only if some run cannot, a vmapped
full-grid epoch (`pgp.scan`, 1 epoch) advances those runs (the others are masked). Each run keeps
its own epoch counter; its outputs go to a (B, epochs) buffer at its own offset.

Every run takes the same decisions as alone, so its numbers equal `run_chunked`'s up to rounding
(vmapped programs; full-grid steps of 1 epoch instead of 4, whose epochs run windowed when they
can, as in `run_chunked`). Used by the sweep's "vmap" execution for accelerators.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.mesh import fast as F
from jaxcal.mesh import pgp

__all__ = ["run_lockstep"]


def _pad(inp: pgp.FilterInputs, chunk: int) -> pgp.FilterInputs:
    z = jnp.concatenate([inp.z, jnp.full((chunk,) + inp.z.shape[1:], jnp.nan, inp.z.dtype)])
    dt = jnp.concatenate([inp.dt, jnp.zeros((chunk,), inp.dt.dtype)])
    return dataclasses.replace(inp, z=z, dt=dt)


def _write(buf, out, k, rows):
    """Rows [k, k + rows) of every FilterOut field of one run's buffer (`rows` static)."""
    return jax.tree.map(lambda b, o: jax.lax.dynamic_update_slice_in_dim(b, o[:rows], k, 0), buf, out)


def _window_step(cfg, prm, inp, st, buf, k, ready, n_ep: int, chunk: int):
    """One run: up to `chunk` windowed epochs from epoch k (none unless `ready`)."""
    z = jax.lax.dynamic_slice_in_dim(inp.z, k, chunk)
    dt = jax.lax.dynamic_slice_in_dim(inp.dt, k, chunk)
    valid = ready & (k + jnp.arange(chunk) < n_ep)
    n = st.win.shape[0]
    small = dataclasses.replace(st, logpost=jnp.zeros((n, 1, 1), st.logpost.dtype))
    part = dataclasses.replace(inp, z=z, dt=dt)
    st2, out, done = pgp.scan_windows(cfg, prm, part, small, valid, k)
    st2 = dataclasses.replace(st2, logpost=st.logpost)
    # rows past `done` are rewritten by the steps that compute them
    return st2, _write(buf, out, k, chunk), k + done.astype(k.dtype)


def _full_step(cfg, prm, inp, st, buf, k, active):
    """One run: one full-grid epoch at epoch k when `active` (else unchanged)."""
    z = jax.lax.dynamic_slice_in_dim(inp.z, k, 1)
    dt = jax.lax.dynamic_slice_in_dim(inp.dt, k, 1)
    st2, out = pgp.scan(cfg, prm, dataclasses.replace(inp, z=z, dt=dt), st, k)
    st2 = jax.tree.map(lambda a, b: jnp.where(active, a, b), st2, st)
    buf2 = _write(buf, out, k, 1)
    buf2 = jax.tree.map(lambda a, b: jnp.where(active, a, b), buf2, buf)
    return st2, buf2, k + active.astype(k.dtype)


@eqx.filter_jit
def _window_batch(cfg, prm, inp, st, buf, k, ready, n_ep, chunk):
    return jax.vmap(lambda p, i, s, b, kk, r: _window_step(cfg, p, i, s, b, kk, r, n_ep, chunk))(
        prm, inp, st, buf, k, ready
    )


@eqx.filter_jit
def _full_batch(cfg, prm, inp, st, buf, k, active):
    return jax.vmap(lambda p, i, s, b, kk, a: _full_step(cfg, p, i, s, b, kk, a))(prm, inp, st, buf, k, active)


@eqx.filter_jit
def _init(cfg, logpost0, inp, n_ep: int, chunk: int):
    """Batched initial states and output buffers (their rows filled as runs advance)."""
    st = jax.vmap(lambda lp: pgp.init_state(cfg, lp))(logpost0)
    b, n = logpost0.shape[:2]
    dtype = logpost0.dtype
    rows = n_ep + chunk
    nan = lambda *s: jnp.full((b, rows) + s, jnp.nan, dtype)  # noqa: E731
    buf = pgp.FilterOut(
        estimate=nan(n, 2),
        raw=nan(n, 2),
        log_mass=nan(n),
        log_evidence=nan(n),
        n_factors=nan(n),
        windowed=jnp.zeros((b, rows), bool),
        small=jnp.zeros((b, rows), bool),
    )
    return st, buf, _pad_batch(inp, chunk)


def _pad_batch(inp, chunk):
    return jax.vmap(lambda i: _pad(i, chunk))(inp)


def run_lockstep(
    cfg: pgp.FilterConfig,
    prm: pgp.FilterParams,
    inp: pgp.FilterInputs,
    logpost0,
    chunk: int = 64,
) -> pgp.FilterOut:
    """B runs of the filter (leading axis of `prm`, `inp`, `logpost0`) on the windowed fast path.

    Args:
        cfg: the common static config; needs `cfg.window` (the fast path) and no snapshots.
        prm, inp, logpost0: batched (B, ...) as for `jax.vmap(pgp.filter_epochs)`; everything runs on
            the device of `logpost0` (the sweep runs one driver per device).
        chunk: epochs per windowed step.

    Returns:
        FilterOut with a leading (B, epochs) axis pair: every run's per-epoch outputs.
    """
    if not cfg.window or cfg.n_snap:
        raise ValueError("run_lockstep needs the windowed fast path and no snapshots")
    n_ep = int(inp.z.shape[1])
    # every array on the device (and sharding) of `logpost0`: the step programs then see the same
    # placements at every call and compile once
    put = lambda x: jax.device_put(x, logpost0.sharding)  # noqa: E731
    prm, inp = put(prm), put(inp)
    st, buf, pinp = _init(cfg, logpost0, inp, n_ep, chunk)
    b, n = logpost0.shape[:2]
    k = put(np.zeros((b,), np.int32))
    need = np.asarray(inp.need)
    log_cells = np.log(np.maximum(np.asarray(inp.mask).reshape(b, n, -1).sum(-1), 1))
    while True:
        kh = np.asarray(k)
        left = kh < n_ep
        if not left.any():
            break
        loc = np.asarray(st.heard).sum(-1) >= need
        held = np.all(np.asarray(st.bound) + log_cells < F.WINDOW_LOG_TOL, -1)
        ready = left & loc.all(-1) & held
        rest = left & ~ready
        if ready.any():
            st, buf, k = _window_batch(cfg, prm, pinp, st, buf, k, put(ready), n_ep, chunk)
            # a run stopped inside its chunk (windows failed): one full-grid epoch next, as alone
            moved = np.asarray(k) - kh
            rest = rest | (ready & (moved < np.minimum(chunk, n_ep - kh)))
        if rest.any():
            st, buf, k = _full_batch(cfg, prm, pinp, st, buf, k, put(rest))
    return jax.tree.map(lambda a: a[:, :n_ep], buf)
