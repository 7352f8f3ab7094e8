"""The filter's kernels: hypotheses (eq. 9-10), one node's epoch on the full grid (eq. 7-12), and one
epoch of every node on windows (`fast.py`), whose outcome is a `WindowStep`."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from jaxcal.mesh import fast as F
from jaxcal.mesh import grid as G
from jaxcal.mesh.pgp.state import FilterConfig, FilterInputs, FilterParams, FilterState

__all__ = [
    "WindowStep",
    "remat",
    "hypotheses",
    "nlos_args",
    "node_update",
    "window_epoch",
    "windows_epoch",
    "skipped_window_step",
]


class WindowStep(eqx.Module):
    """One epoch of every node on its window (`window_epoch`); a1 on its grid row.

    Attributes:
        window: (nodes, W, W) log posteriors in their windows (W = `FilterConfig.window`; an epoch on
            the small window places its result in the big one, -inf outside).
        origin: (nodes, 2) int32 grid indices of each window's first cell.
        bound: (nodes,) log of the largest posterior value outside each window (a1: -inf).
        log_evidence: (nodes,) log normaliser of eq. (12) (`FilterOut.log_evidence`).
        raw: (nodes, 2) eq. (13) estimates [m] before smoothing.
        row: (n,) a1's log posterior on its grid row (`FilterState.row`).
        held: whether the mass outside every window stayed below `fast.WINDOW_LOG_TOL` (else the
            epoch must run again on a bigger window or the full grid).
        small_next: whether the next epoch should try the small window first.
        ran_small: whether this epoch ran on the small window (`window_small_m`).
    """

    window: Float[Array, "nodes w w"]
    origin: Int[Array, "nodes 2"]
    bound: Float[Array, " nodes"]
    log_evidence: Float[Array, " nodes"]
    raw: Float[Array, "nodes 2"]
    row: Float[Array, " n"]
    held: Bool[Array, ""]
    small_next: Bool[Array, ""]
    ran_small: Bool[Array, ""]


def remat(config: FilterConfig, fn):
    """`fn` under `jax.checkpoint` when the filter is differentiated (`config.remat`): a branch of
    `lax.cond` then keeps only its inputs for the backward pass and is recomputed there, instead of
    storing its intermediates (reverse mode of a cond stores the residuals of both branches, the
    branch not taken as zeros). Forward-only runs are unchanged. The time the tuning gradient
    gained came from the per-pair loop bodies (`remat` of `grid.node_loglik_sparse`,
    `fast.ring_loglik_grid`); wrapping these branches alone changed no measured time
    (docs/benchmarks/tuning.md)."""
    return jax.checkpoint(fn) if config.remat else fn


def hypotheses(config: FilterConfig, params: FilterParams, logp: Float[Array, "n c"], cells: Float[Array, "c 2"]):
    """(N, H, 2), (N, H), (N,) hypotheses of all nodes: eq. (10), or eq. (9) for parametric.

    `cells` is (C, 2) shared by all nodes or (N, C, 2) per node (windows)."""
    ca = 0 if cells.ndim == 3 else None
    if config.mode == "pgp" and config.select == "soft":
        assert params.tau_temp is not None, "select='soft' needs FilterParams.tau_temp"
        pos, lw = jax.vmap(G.soft_hypotheses, in_axes=(0, ca, None, None, None))(
            logp, cells, config.n_hyp, params.tau, params.tau_temp
        )
        sig = jnp.broadcast_to(params.sigma_r, logp.shape[:1])
        return pos, lw, sig
    if config.mode == "pgp":
        pos, lw = jax.vmap(G.top_hypotheses, in_axes=(0, ca, None, None))(logp, cells, config.n_hyp, params.tau)
        sig = jnp.broadcast_to(params.sigma_r, logp.shape[:1])
        return pos, lw, sig
    est = jax.vmap(G.window_estimate, in_axes=(0, ca, None))(logp, cells, params.r_est)
    _, cov = jax.vmap(G.mean_cov, in_axes=(0, ca))(logp, cells)
    tr = jnp.maximum(jnp.trace(cov, axis1=1, axis2=2), 0.0)
    # eq. (9): the receiver's own uncertainty is its grid, so only the neighbour's trace is added.
    sig = params.sigma_r + jnp.sqrt(tr)
    return est[:, None, :], jnp.zeros(est.shape[:1] + (1,), est.dtype), sig


def nlos_args(config: FilterConfig, params: FilterParams):
    """The `nlos` argument of `grid.pair_loglik` for the configured range model."""
    return (params.nlos_weight, params.nlos_mean_m) if config.range_model == "mixture" else None


def node_update(config, params, cells, logp_i, mask_i, loc_i, hyps, z_i, use_i, step_m):
    """One node's epoch: motion update (if localised), eq. (11), eq. (12) posterior (C,)."""
    prior = jax.lax.cond(
        loc_i,
        remat(config, lambda lp: G.predict(lp, cells, config.top_k, step_m, params.sigma_v)),
        lambda lp: lp,
        logp_i,
    )
    if config.likelihood == "dense":
        lik = G.node_loglik
    else:
        lik = lambda *a: G.node_loglik_sparse(*a, remat=config.remat)  # noqa: E731
    if config.window and config.mode == "pgp":  # the fast path's full-grid epochs: kernel images
        lik = lambda _cells, *a: F.ring_loglik_grid(config.grid, *a, remat=config.remat)  # noqa: E731
    ll = lik(cells, hyps[0], hyps[1], hyps[2], z_i, use_i, params.p_out, nlos_args(config, params))
    post = jnp.where(mask_i, prior + ll, -jnp.inf)
    lse = jax.nn.logsumexp(post)
    return post - lse, lse - jax.nn.logsumexp(jnp.where(mask_i, prior, -jnp.inf))


def window_epoch(
    config: FilterConfig,
    params: FilterParams,
    inputs: FilterInputs,
    state: FilterState,
    z,
    step_m,
    use,
    log_cells,
    w: int,
):
    """One jacobi epoch on W x W windows (`fast.py`): every node localised, posteriors in `state.win`
    (`config.window` a side); `w` <= `config.window` is the side this epoch runs on (the small window of
    `window_small_m`, or `config.window`), its result is placed in a `config.window` window (-inf
    outside `w`, covered by the bound).

    a1 runs on its whole row instead (`FilterState.row`). Eq. (11) on the windows is
    `fast.ring_loglik` (one kernel image per pair) when every used neighbour's hypotheses fit its
    block and nothing underflows, else `grid.node_loglik` (same values up to rounding).

    Returns:
        a `WindowStep`; its `held` says the new mass outside every window is below
        `fast.WINDOW_LOG_TOL` (else the caller runs the epoch on a bigger window or the full grid
        instead)."""
    grid, wb = config.grid, config.window
    ns = grid.n_side
    n = state.win.shape[0]
    dtype = state.win.dtype
    win = state.win.reshape(n, wb * wb)
    cells_of = jax.vmap(lambda o: F.window_cells(o, grid, wb, dtype))
    wc_old = cells_of(state.org)
    hyps = hypotheses(config, params, win, wc_old)
    row_cells = jnp.stack([grid.axis(dtype), jnp.zeros((ns,), dtype)], axis=-1)
    h1 = hypotheses(config, params, state.row[None], row_cells)
    hyps = tuple(h.at[1].set(h1_[0]) for h, h1_ in zip(hyps, h1, strict=True))
    nlos = nlos_args(config, params)

    def sources(win_i, org_i, wc_i):
        vals, idx = G.top_k(win_i, config.top_k)
        src_idx = org_i[None, :] + jnp.stack([idx // wb, idx % wb], axis=-1)
        flat = src_idx[0, 0] * ns + src_idx[0, 1]
        new_org = F.window_origin(flat, ns, w)
        cells = F.window_cells(new_org, grid, w, dtype)
        prior = F.predict_window(vals, wc_i[idx], cells, step_m, params.sigma_v)
        return vals, src_idx, F.window_origin(flat, ns, wb), new_org, cells, prior

    vals, src_idx, org_b, org, cells, prior = jax.vmap(sources)(win, state.org, wc_old)

    def direct_ll():
        return jax.vmap(G.node_loglik, in_axes=(0, None, None, None, 0, 0, None, None))(
            cells, hyps[0], hyps[1], hyps[2], z, use, params.p_out, nlos
        )

    if config.mode == "pgp":  # hypotheses are grid cells (eq. 10)
        ll, ring_ok = jax.vmap(F.ring_loglik, in_axes=(0, None, None, None, None, None, 0, 0, None, None))(
            org, w, grid, hyps[0], hyps[1], hyps[2], z, use, params.p_out, nlos
        )
        ll = jax.lax.cond(jnp.all(ring_ok), lambda: ll, remat(config, direct_ll))
    else:  # eq. (9): off-grid estimates
        ll = direct_ll()

    def node(vals_i, src_i, org_b_i, org_i, cells_i, prior_i, ll_i, mask_i):
        m = F.window_mask(mask_i, org_i, w)
        post = jnp.where(m, prior_i + ll_i, -jnp.inf)
        lse = jax.nn.logsumexp(post)
        ev = lse - jax.nn.logsumexp(jnp.where(m, prior_i, -jnp.inf))
        kw = dict(n_side=ns, cell_m=grid.cell_m, step_m=step_m, sigma_v=params.sigma_v)
        pb = F.outside_bound(vals_i, src_i, org_i, w=w, **kw)
        post = post - lse
        raw = G.window_estimate(post, cells_i, params.r_est)
        out = post.reshape(w, w)
        if w < wb:  # the small window lies inside the big one centred on the same cell
            big = jnp.full((wb, wb), -jnp.inf, dtype)
            out = jax.lax.dynamic_update_slice(big, out, tuple(org_i - org_b_i))
            small = pb
        elif config.window_small:  # would the small window have held? (lse here >= its lse)
            o_s = F.window_origin(src_i[0, 0] * ns + src_i[0, 1], ns, config.window_small)
            small = F.outside_bound(vals_i, src_i, o_s, w=config.window_small, **kw)
        else:
            small = jnp.asarray(jnp.inf, dtype)
        return out, pb - lse, ev, raw, small - lse

    win, bound, ev, raw, small = jax.vmap(node)(vals, src_idx, org_b, org, cells, prior, ll, inputs.mask)
    # a1 on its row: eq. (7)-(8) from its top_k cells, eq. (11) with a0's hypothesis
    vals, idx = G.top_k(state.row, config.top_k)
    d = G.safe_norm(row_cells[None, :, :] - row_cells[idx][:, None, :])
    prior = jax.nn.logsumexp(vals[:, None] - 0.5 * jnp.square((d - step_m) / params.sigma_v), axis=0)
    ll = G.node_loglik(row_cells, hyps[0], hyps[1], hyps[2], z[1], use[1], params.p_out, nlos)
    m = inputs.mask[1, :, grid.n_half]
    post = jnp.where(m, prior + ll, -jnp.inf)
    lse = jax.nn.logsumexp(post)
    ev = ev.at[1].set(lse - jax.nn.logsumexp(jnp.where(m, prior, -jnp.inf)))
    row = post - lse
    raw = raw.at[1].set(G.window_estimate(row, row_cells, params.r_est))
    bound = bound.at[1].set(-jnp.inf)
    small = small.at[1].set(-jnp.inf)
    ok = jnp.all(bound + log_cells < F.WINDOW_LOG_TOL)
    # try the small window next only with room to spare: a failed try costs a second epoch
    tol = F.WINDOW_LOG_TOL - F.SMALL_WINDOW_MARGIN
    small_next = bool(config.window_small) & jnp.all(small + log_cells < tol)
    return WindowStep(
        window=win,
        origin=org_b,
        bound=bound,
        log_evidence=ev,
        raw=raw,
        row=row,
        held=ok,
        small_next=small_next,
        ran_small=jnp.asarray(w < wb),
    )


def windows_epoch(
    config: FilterConfig,
    params: FilterParams,
    inputs: FilterInputs,
    state: FilterState,
    z,
    step_m,
    use,
    log_cells,
) -> WindowStep:
    """A windowed epoch on the small window (`config.window_small`) when the last epoch says it may
    hold, falling back to the big window (`config.window`) when its bound fails; the caller falls
    back to the full grid when both fail (`WindowStep.held` false)."""

    def run(w):
        return window_epoch(config, params, inputs, state, z, step_m, use, log_cells, w)

    def big():
        return run(config.window)

    if not config.window_small:
        return big()

    def small_first():
        step = run(config.window_small)
        return jax.lax.cond(step.held, lambda: step, big)

    return jax.lax.cond(state.small, small_first, big)


def skipped_window_step(state: FilterState) -> WindowStep:
    """The `WindowStep` of an epoch that did not run on the windows: `state`'s windows unchanged,
    `held` false (the caller then runs the full grid, or stops)."""
    n = state.win.shape[0]
    dtype = state.win.dtype
    no = jnp.asarray(False)
    return WindowStep(
        window=state.win,
        origin=state.org,
        bound=state.bound,
        log_evidence=jnp.zeros((n,), dtype),
        raw=jnp.full((n, 2), jnp.nan, dtype),
        row=state.row,
        held=no,
        small_next=state.small,
        ran_small=no,
    )
