"""A one-sided NLOS excess tied to place, on every range (`gp` with `model=excess`).

Model per anchor, every range, e_t = r_t - |p_t - a| - b:

    e_t ~ (1 - eps) [(1 - pi(c_t)) LOS(e_t) + pi(c_t) NLOS(e_t)] + eps / D,

LOS = N(0, s_L^2) convolved with an exponential excess of mean tau_L (an exponentially modified Gaussian, EMG),
NLOS = EMG(mu, s_N, tau_N) with mu >= 0: a non-line-of-sight range is never shorter than the
line-of-sight one (the excess delay through or around an obstacle is positive, `jaxcal.sim.channel`), so the
anchor's cone plus b is the *lower* edge of the ranges, not their centre. eps / D is a gross-outlier floor
(D: the span of the anchor's ranges). pi(c) is the NLOS probability of the route cell c the tag is in (square
(x, y) cells, the box of the anchor's tag positions cut into `excess_cells` cells along its longer side): whether
a link is NLOS is a function of where the platform is, so the ranges of one place share it.

Why: a symmetric heavy-tailed loss (nls's Cauchy, the GP's Student-t weights) centres the cone on the
*majority* of the ranges. Where most links of a stretch are NLOS it takes "cone + mu on the stretches in a zone"
for "the anchor a bit further away", and the error follows the zones' layout. The one-sided mixture keeps
mu as a separate, positive offset, and pi(c) tells per place which ranges carry it.

Fit (generalised EM, one `jax.lax.scan` of `excess_rounds` rounds per anchor, anchors in `lax.map`): with pi
fixed, the anchor, b and the class parameters minimise the negative log likelihood (Optimistix BFGS, seeded at
`nls` with b at the lower tail of nls's residuals); then pi(c) = (sum_c gamma_t + k pi_bar) / (n_c + k), gamma_t
the posterior NLOS probability of range t, shrunk to the anchor's mean pi_bar by k = `excess_prior` pseudo
ranges (a cell with few ranges keeps the anchor's average). Each round does not lower the likelihood. Speed
(fourteenth round, 8x on 1e5 ranges): from the second round on, BFGS starts from the exact inverse Hessian at the
last round's answer (`jaxcal.solver.StartedBFGS`: about 16 steps a round instead of 60, the same minimum), and the EM
runs on at most `excess_max_ranges` (4000) ranges per anchor, evenly spaced in time (`thin_indices`; ranges at
tens of hertz repeat each other's errors: on the simulated campus, odd seeds, 4000 were as accurate as all).
On a flat path the height is held at `nls`'s. Covariance: the anchor block of the inverse Hessian of the
negative log likelihood at the last pi (Laplace), widened to `nls`'s reported covariance by the shared driver
(`gp_path.calibrate_every_range`, also the fallback and the report). Not a Gaussian process: the "field" is
the cell-wise NLOS probability, the per-place structure the GP's f was meant to carry, in a one-sided form.
"""

from __future__ import annotations

from types import SimpleNamespace

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from jaxcal import solver as S
from jaxcal.data import Result
from jaxcal.shapes import padded_length
from jaxcal.trajectory.gp_kernel import Hyper, _cone, laplace_covariance

__all__ = ["emg_logpdf", "ExcessModel", "excess_nll", "fit_excess_all", "thin_indices", "calibrate_excess"]

# a weak Gaussian prior on the six class parameters about their start (sd in their unconstrained units): keeps
# the mixture identifiable where one class is empty (pi -> 0: its shape has no data), so BFGS and the Hessian stay
# finite; a few ranges overrule it
_SHAPE_SD = 2.0
# probabilities of a cell are kept inside [_PI_MIN, 1 - _PI_MIN]; eps (outliers) inside [_EPS_MIN, 0.5]
_PI_MIN, _EPS_MIN = 1e-3, 1e-4


def emg_logpdf(x, mu, sigma, tau):
    """log density of the exponentially modified Gaussian N(mu, sigma^2) + Exp(mean tau) at x (any shape):
    log(1/tau) + (mu - x) / tau + sigma^2 / (2 tau^2) + log Phi((x - mu - sigma^2 / tau) / sigma), with
    `log_ndtr` for the tail (stable where tau << sigma and far from the mode)."""
    lam = 1.0 / tau
    z = (x - mu - sigma**2 * lam) / sigma
    return jnp.log(lam) + lam * (mu - x) + 0.5 * (sigma * lam) ** 2 + jax.scipy.special.log_ndtr(z)


class ExcessModel(eqx.Module):
    """Anchor (3,) [m], range bias b [m] and the class parameters, unconstrained: s_L, tau_L, mu, s_N, tau_N each
    mapped log-uniformly into its physical interval (`_LO`, `_HI`), and logit eps."""

    anchor: Float[Array, ...]
    bias: Float[Array, ...]
    shape: Float[Array, " 6"]


# physical ranges of the class parameters [m] (s_L, tau_L, mu, s_N, tau_N): every parameter is a log-uniform map of
# its unconstrained value into them, so a class left without ranges cannot run off (an s_L of 1e8 m made the LOS
# class an outlier sink, a b 0.6 m low made every range NLOS)
_LO = np.array([0.005, 0.002, 0.01, 0.01, 0.01])
_HI = np.array([0.5, 0.5, 3.0, 1.0, 5.0])


def _to_bounded(u, lo, hi):
    return jnp.exp(jnp.log(lo) + (jnp.log(hi) - jnp.log(lo)) * jax.nn.sigmoid(u))


def _from_bounded(v, lo, hi):
    f = jnp.clip((jnp.log(v) - jnp.log(lo)) / (jnp.log(hi) - jnp.log(lo)), 0.02, 0.98)
    return jnp.log(f) - jnp.log1p(-f)


def _classes(th: ExcessModel):
    """(s_L, tau_L, mu, s_N, tau_N, eps) from the unconstrained `th.shape`."""
    v = _to_bounded(th.shape[:5], _LO, _HI)
    return v[0], v[1], v[2], v[3], v[4], _EPS_MIN + (0.5 - _EPS_MIN) * jax.nn.sigmoid(th.shape[5])


def _log_parts(th: ExcessModel, x, r, log_d):
    """(log LOS, log NLOS, log outlier) densities of every range (n,) under `th`."""
    e = r - _cone(x, th.anchor) - th.bias
    s_l, t_l, mu, s_n, t_n, eps = _classes(th)
    los = jnp.log1p(-eps) + emg_logpdf(e, 0.0, s_l, t_l)
    nlos = jnp.log1p(-eps) + emg_logpdf(e, mu, s_n, t_n)
    return los, nlos, jnp.log(eps) - log_d


def excess_nll(th: ExcessModel, x, r, mask, pi, log_d) -> Float[Array, ""]:
    """-log p(r | th, pi) of the one-sided mixture (module doc) over the valid ranges.

    Args:
        th: parameters. x: (n, 3) tag positions [m]. r: (n,) ranges [m]. mask: (n,) valid.
        pi: (n,) NLOS prior of each range (its cell's). log_d: log of the outlier span D [m].
    """
    los, nlos, out = _log_parts(th, x, r, log_d)
    mix = jnp.logaddexp(jnp.log1p(-pi) + los, jnp.log(pi) + nlos)
    return -jnp.sum(jnp.where(mask, jnp.logaddexp(mix, out), 0.0))


def _em(init, held, fz, shape0, xc, r, m, c, sub, log_d, n_cells: int, rounds: int, prior: float, max_steps, newton):
    """The generalised EM of one anchor (module doc) on the ranges `sub` ((k,) indices, -1 padding) of its centred
    positions xc (n, 3), ranges r, mask m and cells c (n,): `rounds` rounds (one `lax.scan`) of BFGS over the flat
    (anchor, bias, shape) at fixed cell probabilities, then the cells' probabilities from the responsibilities.
    log pi and log(1 - pi) of every range are computed once per round, outside the BFGS loop.

    Returns:
        (ExcessModel, (n_cells + 1,) NLOS probability of each cell (the padding cell's unused), outcome codes
        (rounds,)).
    """
    ok = sub >= 0
    idx = jnp.where(ok, sub, 0)
    xs, rs, ms, cs = xc[idx], r[idx], m[idx] & ok, jnp.where(ok, c[idx], n_cells)
    ws = ms.astype(xc.dtype)
    ns = jnp.maximum(jnp.sum(ws), 1.0)
    y0, unravel = jax.flatten_util.ravel_pytree(init)
    # a flat path (not fz): the height is held, its row of the Hessian is zero; a unit curvature keeps the start finite
    fixed_z = jnp.zeros_like(y0).at[2].set(jnp.where(fz, 0.0, 1.0))

    def loss(y, args):
        log_pi, log_1m_pi = args
        th = held(unravel(y))
        los, nlos, out = _log_parts(th, xs, rs, log_d)
        mix = jnp.logaddexp(log_1m_pi + los, log_pi + nlos)
        nll = -jnp.sum(jnp.where(ms, jnp.logaddexp(mix, out), 0.0))
        return (nll + 0.5 * jnp.sum(((th.shape - shape0) / _SHAPE_SD) ** 2)) / ns

    def round_(carry, first):
        y, pi_c = carry
        pi = pi_c[cs]
        args = (jnp.log(pi), jnp.log1p(-pi))
        if newton:
            # the first round from the identity (optx.BFGS's start), the others from the exact Hessian, in one
            # BFGS program (the first round outside the scan compiled a second BFGS: 2-3 s of XLA compilation)
            h_inv = jax.lax.cond(
                first,
                lambda: jnp.eye(y.size, dtype=y.dtype),
                lambda: S.newton_start(lambda v, a: loss(v, a) + 0.5 * jnp.sum(fixed_z * v**2), y, args),
            )
            solver: optx.AbstractMinimiser = S.StartedBFGS(rtol=1e-7, atol=1e-7, hessian_inv=h_inv)
        else:
            solver = optx.BFGS(rtol=1e-7, atol=1e-7)
        sol = optx.minimise(loss, solver, y, args=args, max_steps=max_steps, throw=False)
        fine = jnp.isfinite(loss(sol.value, args))
        y = jnp.where(fine, jax.flatten_util.ravel_pytree(held(unravel(sol.value)))[0], y)
        los, nlos, _ = _log_parts(unravel(y), xs, rs, log_d)
        gamma = jax.nn.sigmoid(args[0] + nlos - args[1] - los)
        gamma = jnp.where(ms, gamma, 0.0)
        pi_bar = jnp.sum(gamma) / ns
        num = jax.ops.segment_sum(gamma, cs, num_segments=n_cells + 1)
        cnt = jax.ops.segment_sum(ws, cs, num_segments=n_cells + 1)
        pi_c = jnp.clip((num + prior * pi_bar) / (cnt + prior), _PI_MIN, 1.0 - _PI_MIN)
        return (y, pi_c), S.outcome(sol)

    pi0 = jnp.full(n_cells + 1, 0.5, xc.dtype)
    # the first round from the identity: far from the optimum (the nls start) the Hessian is indefinite and a
    # Newton start could lead BFGS to another local minimum of the mixture (1 of 20 test seeds did); from the
    # second round on the start is the last round's minimum, where the exact Hessian is a safe start
    (y, pi_c), codes = jax.lax.scan(round_, (y0, pi0), jnp.arange(rounds) == 0)
    return unravel(y), pi_c, codes


@eqx.filter_jit
def fit_excess_all(
    x,
    r,
    mask,
    cells,
    a0,
    b0,
    free_z,
    n_cells: int,
    rounds: int,
    prior: float,
    max_steps: int,
    sub=None,
    newton: bool = True,
):
    """Every anchor (`lax.map`): x (A, n, 3), r / mask / cells (A, n) (cells: labels 0..n_cells-1, padding
    n_cells), seeds a0 (A, 3), b0 (A,), free_z (A,) whether the height is fitted.

    Args:
        sub: (A, k) indices of the ranges the EM runs on (-1: padding; `thin_indices`), or None: every range. The
            start and the covariance use every range (the cells' probabilities apply to all of them).
        newton: from the second round on, BFGS starts from the exact inverse Hessian at the last round's answer
            (`jaxcal.solver.StartedBFGS`: about 16 steps instead of 60 from the identity); False: from the
            identity in every round (the reference the tests compare with; same minimum per round).

    Returns:
        (anchor (A, 3), covariance (A, 3, 3), bias (A,), Hyper (log s_L, log mu, log pi_bar: for the report),
        outcome codes (A,)).
    """
    if sub is None:
        sub = jnp.broadcast_to(jnp.arange(r.shape[1]), r.shape)

    def one(x, r, m, c, a0, b0, fz, sub):
        w = m.astype(x.dtype)
        nv = jnp.maximum(jnp.sum(w), 1.0)
        origin = jnp.sum(x * w[:, None], axis=0) / nv
        xc = jnp.where(m[:, None], x - origin, 0.0)
        z0 = a0[2] - origin[2]
        e0 = jnp.where(m, r - _cone(xc, a0 - origin) - b0, jnp.nan)
        q10, q50 = jnp.nanpercentile(e0, jnp.array([10.0, 50.0]))
        mad = jnp.nanmedian(jnp.abs(e0 - q50))
        sd = jnp.maximum(1.4826 * mad, 0.02)
        lo_r = jnp.min(jnp.where(m, r, jnp.inf))
        hi_r = jnp.max(jnp.where(m, r, -jnp.inf))
        log_d = jnp.log(jnp.maximum(hi_r - lo_r, 1.0) + 10.0 * sd)
        # b at the lower edge of nls's residuals (the LOS level), mu the gap to their median
        mu0 = jnp.maximum(q50 - q10, 0.05)
        start = jnp.stack([0.5 * sd, 0.25 * sd, mu0, sd, sd])
        shape0 = jnp.concatenate([_from_bounded(start, _LO, _HI), jnp.array([-3.0], x.dtype)])
        init = ExcessModel(a0 - origin, b0 + q10, shape0)

        def held(th):  # a flat path does not observe the height: held at the start's
            return eqx.tree_at(lambda t: t.anchor, th, th.anchor.at[2].set(jnp.where(fz, th.anchor[2], z0)))

        def objective(t, pi):
            prior_shape = 0.5 * jnp.sum(((t.shape - shape0) / _SHAPE_SD) ** 2)
            return excess_nll(held(t), xc, r, m, pi, log_d) + prior_shape

        em = (log_d, n_cells, rounds, prior, max_steps, newton)
        th, pi_c, codes = _em(init, held, fz, shape0, xc, r, m, c, sub, *em)
        pi = pi_c[c]
        cov = laplace_covariance(lambda t: objective(t, pi), th)
        keep = jnp.stack([1.0, 1.0, jnp.where(fz, 1.0, 0.0)])
        s_l, _, mu, _, _, _ = _classes(th)
        report = Hyper(jnp.log(s_l), jnp.log(mu), jnp.log(jnp.sum(jnp.where(m, pi, 0.0)) / nv))
        return th.anchor + origin, cov * keep[:, None] * keep[None, :], th.bias, report, codes[-1]

    return jax.lax.map(lambda a: one(*a), (x, r, mask, cells, a0, b0, free_z, sub))


def thin_indices(mask: np.ndarray, k: int) -> np.ndarray:
    """(A, min(k, L)) indices of at most `k` valid ranges per anchor, evenly spaced in time over its valid ones (all
    of them where it has no more), -1 padding; k = 0: every valid range. L: the most valid ranges of an anchor,
    padded (`jaxcal.shapes.padded_length`). Host-side NumPy.

    Ranges taken at tens of hertz repeat each other's errors (an NLOS state, a pose error persist for seconds), so
    evenly spaced ones keep the information of the route while the EM's cost falls with their number
    (docs/benchmarks/trajectory.md, fourteenth round: the accuracy against k)."""
    mask = np.asarray(mask, dtype=bool)
    counts = mask.sum(axis=1)
    most = padded_length(int(max(1, counts.max(initial=0))))  # one shape for campaigns of similar size
    width = most if k <= 0 else min(k, most)
    out = np.full((mask.shape[0], width), -1, dtype=np.int64)
    for a in range(mask.shape[0]):
        idx = np.flatnonzero(mask[a])
        if idx.size > width:
            idx = idx[np.round(np.linspace(0.0, idx.size - 1.0, width)).astype(np.int64)]
        out[a, : idx.size] = idx
    return out


def calibrate_excess(dataset, p, groups, info, planar) -> Result:
    """`gp` with `model=excess` (module doc): `nls` start, the one-sided mixture on every range."""
    from jaxcal.trajectory import nls
    from jaxcal.trajectory.gp_path import calibrate_every_range

    free_z = jnp.asarray(~np.asarray(planar, dtype=bool))
    labels, n_cells = nls.route_cells(groups, SimpleNamespace(cov_cell_m=0.0, cov_cells=p.excess_cells))
    cells = jnp.asarray(labels)
    sub = jnp.asarray(thin_indices(np.asarray(groups.mask), p.excess_max_ranges))

    def fit(args, steps):
        pos, rng_m, mask, _, a0, b0 = args
        return fit_excess_all(
            pos, rng_m, mask, cells, a0, b0, free_z, n_cells, p.excess_rounds, p.excess_prior, steps, sub
        )

    names = ("los_sd_m", "nlos_excess_m", "nlos_fraction")
    return calibrate_every_range(dataset, p, groups, info, planar, "excess", fit, names)
