"""The PGP filter's epoch scan in checkpointed segments: reverse mode in O(sqrt(K)) carries.

Reverse-mode differentiation of a `lax.scan` over K epochs stores what the backward pass needs of
every epoch. With the epoch body `jax.checkpoint`ed (`FilterConfig.remat`) that is one carry per
epoch: `(nodes, cells)` log posteriors, 12 x 15,129 x 8 B = 1.45 MB at torgau's 0.5 m grid, 2.9 GB
for 2,000 epochs. Here the K epochs run as an outer `lax.scan` over `ceil(K / S)` segments of S
epochs, each segment an inner scan (the filter's own `pgp.scan`) wrapped in `jax.checkpoint`: the
forward pass keeps only the carries between segments, and the backward pass re-runs one segment at a
time, keeping its S carries. With S ~ sqrt(K) the memory is ~2 sqrt(K) carries (~130 MB for
torgau) for one extra forward pass. Same epochs, same numbers as `pgp.run_filter` (tested).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxcal.mesh import pgp

__all__ = ["segment_length", "filter_segmented"]


def segment_length(n_epochs: int) -> int:
    """The segment length S: about sqrt(K), which minimises the stored carries (K / S + S).

    A divisor of K is preferred when one keeps K / S + S within 10 % of that minimum: then no
    shorter last segment runs as a second scan, whose filter body is traced, lowered and compiled
    a second time (measured on torgau's 200 tuning epochs: S = 15 gives 13 segments and a tail
    of 5, two copies of the filter in the gradient's program; S = 10 gives one)."""
    k = max(int(n_epochs), 1)
    s = max(1, math.ceil(math.sqrt(k)))
    best = min((d for d in range(1, k + 1) if k % d == 0), key=lambda d: (k // d + d, -d))
    return best if k // best + best <= 1.1 * (math.ceil(k / s) + s) else s


def filter_segmented(
    cfg: pgp.FilterConfig,
    prm: pgp.FilterParams,
    inp: pgp.FilterInputs,
    logpost0: Float[Array, "n nx ny"],
    segment: int | None = None,
    state: pgp.FilterState | None = None,
    k0=0,
) -> tuple[pgp.FilterState, pgp.FilterOut]:
    """`pgp.run_filter`'s epochs as checkpointed segments (differentiable, sqrt-N memory).

    Args:
        cfg, prm, inp, logpost0: as `pgp.prepare` returns them (any `select`, `likelihood`).
        segment: epochs per segment S (None: `segment_length(K)`). K need not be a multiple of S:
            the last K mod S epochs run as one more checkpointed scan (an epoch without ranges is
            not a no-op, so the data are never padded).
        state: the state before `inp`'s first epoch (None: `pgp.init_state(cfg, logpost0)`),
            e.g. `pgp.advance_chunked`'s after the earlier epochs of a recording (windowed or not).
        k0: index of `inp`'s first epoch in the recording (snapshots).

    Returns:
        (final FilterState with the full-grid `logpost`, FilterOut of all K epochs), as
        `pgp.run_filter`.
    """
    k = int(inp.z.shape[0])
    s = segment_length(k) if segment is None else max(1, min(int(segment), max(k, 1)))
    q, r = divmod(k, s)
    inner = dataclasses.replace(cfg, remat=True)  # each epoch recomputed in the backward pass

    # the filter's own epoch scan, one segment
    def run(st, z, dt, k0):
        return pgp.scan(inner, prm, dataclasses.replace(inp, z=z, dt=dt), st, k0)

    seg = jax.checkpoint(run)
    st = pgp.init_state(cfg, logpost0) if state is None else state
    outs = []
    if q:
        z = inp.z[: q * s].reshape((q, s) + inp.z.shape[1:])
        dt = inp.dt[: q * s].reshape(q, s)
        ks = k0 + jnp.arange(q) * s

        def body(st, x):
            return seg(st, *x)

        st, out = jax.lax.scan(body, st, (z, dt, ks))
        outs.append(jax.tree.map(lambda a: a.reshape((q * s,) + a.shape[2:]), out))
    if r or not q:
        st, out = seg(st, inp.z[q * s :], inp.dt[q * s :], k0 + jnp.asarray(q * s))
        outs.append(out)
    out = outs[0] if len(outs) == 1 else jax.tree.map(lambda *a: jnp.concatenate(a), *outs)
    return pgp.full_state(cfg, st), out
