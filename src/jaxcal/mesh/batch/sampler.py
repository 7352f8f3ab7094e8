"""`estimate=mean`: the pair-level posterior of the positions, sampled by Hamiltonian Monte Carlo
(`posterior_mean`), and the graph checks that decide before any sampling whether it can be sampled
(`posterior_defect`)."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from jaxcal.mesh.batch.model import _errors, _Numbers, _prior_scales, _State
from jaxcal.mesh.batch.params import Observations

_LEAPFROG = 16  # leapfrog steps per HMC transition of `posterior_mean`


_BURN = 250  # most transitions of each of the two burn-in phases of `posterior_mean`


_BLOCK = 125  # transitions per block of `posterior_mean` after the burn-in (its stopping rule's unit)


_ACCEPT = 0.8  # mean acceptance probability that the step size adapts to


def _split_rhat(s1: Array, s2: Array, n: int | Array) -> Array:
    """Split-chain potential scale reduction R-hat per coordinate (Gelman et al.).

    Args:
        s1, s2: (2, C, P) sums and sums of squares of the two halves of C chains, n draws each.
    """
    mean = (s1 / n).reshape(-1, s1.shape[-1])
    var = ((s2 - s1 * s1 / n) / jnp.maximum(n - 1, 1)).reshape(-1, s1.shape[-1])
    w = jnp.mean(var, axis=0)
    b = n * jnp.var(mean, axis=0, ddof=1)
    var_plus = (n - 1) / n * w + b / n
    return jnp.sqrt(var_plus / jnp.maximum(w, 1e-300))


def _pair_scale(e: Array, real: Array, n_par: Array) -> Array:
    """Robust scale [m] of pair errors: 1.4826 MAD, inflated for the fitted parameters (sqrt(M / (M - P)))."""
    m = jnp.sum(real)
    mad = jnp.nanmedian(jnp.where(real, jnp.abs(e), jnp.nan))
    return jnp.maximum(1.4826 * mad * jnp.sqrt(m / jnp.maximum(m - n_par, 1.0)), 1e-6)


@eqx.filter_jit
def _own_posterior_mean(
    free: Array,
    template: Array,
    mask: Array,
    offset: Array,
    node_offsets: Array,
    observations: Observations,
    numbers: _Numbers,
    key: Array,
    nu: Array,
    n_chains: int,
    n_steps: int,
    sample_node_offsets: bool = True,
    mcse: float = 0.0,
):
    """Posterior mean and covariance of the free frame coordinates (and offsets) (`estimate=mean`).

    The least-squares / robust fit is the posterior *mode*. Where the geometry is weak (a direction the
    ranges pin down only to second order, e.g. nodes nearly in one plane or on one line), the posterior is
    curved and skewed, and its mode sits away from its mean; the mean is the estimate with the least
    expected squared error. Model: one observation per pair (`observations`, the per-pair median summary), each
    error Student-t with `nu` degrees of freedom and a common scale s = 1.4826 MAD(e) sqrt(M / (M - P)) of
    the fit's pair errors (per-pair systematic errors dominate on real meshes: repeated ranges of a pair
    are not independent, so the pair, not the single range, is the unit); flat prior on positions, the
    offsets' priors of `_prior_scales`. Sampled by Hamiltonian Monte Carlo (`_LEAPFROG` leapfrog steps per
    transition, `n_chains` vmapped chains started at the fit); a quarter of `n_steps` (at most 2 `_BURN`) is burn-in:
    its first half runs whitened by the Laplace covariance and estimates the posterior covariance, which
    whitens the rest; the step size adapts during the burn-in to a mean acceptance probability of 0.8.

    Args:
        free: (F,) free coordinates of the fit; template: (m, D) frame coordinates (fixed ones 0);
        mask: (m, D) bool, which entries of `template` are free; offset, node_offsets: the fit's range offsets c and b;
        observations: pair observations (padding has weight 0); numbers: `_Numbers` of the fit; key: PRNG key;
        nu: Student-t degrees of freedom; n_chains, n_steps: static sampler sizes.
        mcse: static; > 0: stop after the burn-in once the Monte Carlo error of the mean is below mcse
            posterior sd (and split R-hat below 1.01) in every free coordinate, checked every two blocks of
            `_BLOCK` transitions; 0: run all n_steps.
        sample_node_offsets: static; False when the model has no per-node offsets (`numbers.use_b` off): they
            then enter no range, their posterior is their prior (mean 0, sd `node_bias_sigma_m`,
            independent of the rest), and they are returned as such instead of being sampled (P = F + 1
            sampled dimensions instead of F + 1 + n: the whitening costs O(P^2) per gradient).

    Returns:
        (mean (F + 1 + n,), covariance (F + 1 + n, F + 1 + n), acceptance rate, max split R-hat over the
        free coordinates, transitions run per chain (burn-in included), the Laplace covariance of the same
        model with a Gaussian likelihood of the same scale, (J^T W J / s^2 + prior)^-1 at the fit (P, P):
        the linearisation that `solve` compares the samples with).
    """
    f, n_b = free.shape[0], node_offsets.shape[0]
    idx = jnp.nonzero(mask.ravel(), size=f)[0]
    b_fixed = jnp.zeros_like(node_offsets)
    theta0 = jnp.concatenate([free, jnp.reshape(offset, (1,))] + ([node_offsets] if sample_node_offsets else []))
    p_dim = theta0.shape[0]

    def errs(theta):
        x = template.ravel().at[idx].set(theta[:f]).reshape(template.shape)
        return _errors(_State(x, theta[f], theta[f + 1 :] if sample_node_offsets else b_fixed), observations, numbers)

    real = observations.w > 0
    e0 = errs(theta0)
    n_par = f + numbers.use_c + numbers.use_b * n_b
    scale = _pair_scale(e0, real, n_par)
    sc, sb = _prior_scales(numbers)
    prior_prec = jnp.concatenate([jnp.zeros(f), jnp.stack([1.0 / sc**2]), jnp.full(n_b, 1.0 / sb**2)])
    prior_prec = prior_prec[:p_dim]

    def logp(theta):
        e = errs(theta)
        ll = -0.5 * (nu + 1.0) * jnp.sum(observations.w * jnp.log1p((e / scale) ** 2 / nu))
        return ll - 0.5 * jnp.sum(prior_prec * theta * theta)

    # Hamiltonian Monte Carlo in whitened coordinates theta = center + root @ u: root @ root.T is the
    # Laplace covariance first, then (from the second half of the burn-in on) the burn-in's sample
    # covariance, which follows a curved, weakly determined posterior. The leapfrog step size adapts
    # during the burn-in towards a mean acceptance probability of 0.8.
    jac = jax.jacfwd(errs)(theta0)
    info = (jac.T * observations.w) @ jac / scale**2 + jnp.diag(prior_prec)

    def sqrt_cov(cov):
        lam, vec = jnp.linalg.eigh(0.5 * (cov + cov.T))
        return vec * jnp.sqrt(jnp.maximum(lam, 1e-12 * jnp.max(lam)))

    def transition(carry, k, center, root, adapt):
        u, lp, eps, acc = carry  # u: (C, P) whitened positions, lp: (C,), eps: scalar step size
        k1, k2, k3 = jax.random.split(k, 3)
        lp_u = lambda v: logp(center + root @ v)  # noqa: E731
        grad = jax.vmap(jax.grad(lp_u))
        h = eps * jax.random.uniform(k3, minval=0.8, maxval=1.2)  # jittered step size
        mom = jax.random.normal(k1, u.shape)

        def leap(state, _):  # the gradient at q is carried: one evaluation per leapfrog step, not two
            q, pm, g = state
            pm = pm + 0.5 * h * g
            q = q + h * pm
            g = grad(q)
            pm = pm + 0.5 * h * g
            return (q, pm, g), None

        (q, pm, _), _ = jax.lax.scan(leap, (u, mom, grad(u)), None, length=_LEAPFROG)
        lq = jax.vmap(lp_u)(q)
        log_ratio = lq - lp - 0.5 * jnp.sum(pm * pm - mom * mom, axis=-1)
        log_ratio = jnp.where(jnp.isfinite(log_ratio), log_ratio, -jnp.inf)
        ok = jnp.log(jax.random.uniform(k2, lp.shape)) < log_ratio
        p_acc = jnp.exp(jnp.minimum(log_ratio, 0.0))
        eps = jnp.where(adapt, eps * jnp.exp(jnp.mean(p_acc) - 0.8), eps)
        u = jnp.where(ok[:, None], q, u)
        return (u, jnp.where(ok, lq, lp), eps, acc + ok), center + u @ root.T

    def run(carry, k, n, center, root, adapt):
        def body(state, kk):
            carry, s1, s2, outer = state
            carry, th = transition(carry, kk, center, root, adapt)
            return (carry, s1 + th, s2 + th * th, outer + th.T @ th), None

        zeros = jnp.zeros((n_chains, p_dim))
        carry = (carry[0], carry[1], carry[2], jnp.zeros(n_chains))
        (carry, s1, s2, outer), _ = jax.lax.scan(
            body, (carry, zeros, zeros, jnp.zeros((p_dim, p_dim))), jax.random.split(k, n)
        )
        return carry, s1, s2, outer

    def moments(s1, outer, n):
        mean = jnp.sum(s1, axis=0) / n
        return mean, outer / n - jnp.outer(mean, mean)

    def rewhiten(carry, center, root, new_center, new_root):
        th = center + carry[0] @ root.T
        u = jnp.linalg.solve(new_root, (th - new_center).T).T
        lp = jax.vmap(lambda v: logp(new_center + new_root @ v))(u)
        return (u, lp, carry[2], carry[3])

    k0, kb1, kb2, ka = jax.random.split(key, 4)
    lap = jnp.linalg.inv(info)
    root = sqrt_cov(lap)
    u0 = 0.1 * jax.random.normal(k0, (n_chains, p_dim))
    carry = (u0, jax.vmap(lambda v: logp(theta0 + root @ v))(u0), jnp.asarray(0.5 / p_dim**0.25), jnp.zeros(n_chains))
    # burn-in: a quarter of n_steps, at most 2 _BURN (the stopping rule after it decides how long to sample)
    burn1 = min(n_steps // 8, _BURN)
    burn2 = min(n_steps // 4 - n_steps // 8, _BURN)
    carry, s1, _, outer = run(carry, kb1, burn1, theta0, root, True)
    center, cov_burn = moments(s1, outer, burn1 * n_chains)
    new_root = sqrt_cov(cov_burn + jnp.diag(1e-12 + 1e-9 * jnp.diag(cov_burn)))
    carry = rewhiten(carry, theta0, root, center, new_root)
    root = new_root
    carry, _, _, _ = run(carry, kb2, burn2, center, root, True)
    # After the burn-in: blocks of `block` transitions, up to the rest of n_steps; with `mcse` > 0 the
    # sampler stops at an even number of blocks (>= 4) once the Monte Carlo error of the mean, estimated
    # from the spread of the chains' means, is below mcse posterior sd and split R-hat below 1.01 in
    # every free coordinate (a well-determined posterior mixes in a few hundred transitions; the
    # whitened gradient costs O(P^2) each).
    n_blk = max(2 * ((n_steps - burn1 - burn2) // (2 * _BLOCK)), 2)
    block = (n_steps - burn1 - burn2) // n_blk
    zeros_blk = jnp.zeros((n_blk, n_chains, p_dim))
    ids = jnp.arange(n_blk)

    def split(k, s):  # the (2, C, P) sums of the first and the second half of the k blocks run
        first = (ids < k // 2)[:, None, None]
        second = ((ids >= k // 2) & (ids < k))[:, None, None]
        return jnp.stack([jnp.sum(jnp.where(first, s, 0.0), axis=0), jnp.sum(jnp.where(second, s, 0.0), axis=0)])

    def converged(k, s1k, s2k):
        h1, h2 = split(k, s1k), split(k, s2k)
        n_half = (k // 2) * block
        rhat = jnp.max(_split_rhat(h1[..., :f], h2[..., :f], n_half))
        chain_mean = (h1[0] + h1[1]) / (2 * n_half)  # (C, P)
        var = jnp.sum(h2[0] + h2[1], axis=0) / (2 * n_half * n_chains) - jnp.mean(chain_mean, axis=0) ** 2
        err2 = jnp.var(chain_mean, axis=0, ddof=1) / n_chains  # squared Monte Carlo error of the mean
        small = jnp.all(err2[:f] <= mcse**2 * jnp.maximum(var[:f], 1e-300))
        return (k >= 4) & (k % 2 == 0) & (rhat < 1.01) & small

    def more(state):
        _, k, s1k, s2k, _ = state
        return (k < n_blk) & ~((mcse > 0) & converged(k, s1k, s2k))

    def one_block(state):
        carry, k, s1k, s2k, outer = state
        carry, s1, s2, o = run(carry, jax.random.fold_in(ka, k), block, center, root, False)
        accepted = carry[3] + state[0][3]  # run() restarts the acceptance count
        return ((carry[0], carry[1], carry[2], accepted), k + 1, s1k.at[k].set(s1), s2k.at[k].set(s2), outer + o)

    carry = (carry[0], carry[1], carry[2], jnp.zeros(n_chains))
    carry, k, s1k, s2k, outer = jax.lax.while_loop(
        more, one_block, (carry, jnp.asarray(0), zeros_blk, zeros_blk, jnp.zeros((p_dim, p_dim)))
    )
    n_draws = k * block
    accept = jnp.sum(carry[3]) / (n_draws * n_chains)
    mean, cov = moments(jnp.sum(s1k, axis=0), outer, n_draws * n_chains)
    rhat = _split_rhat(split(k, s1k)[..., :f], split(k, s2k)[..., :f], (k // 2) * block)
    cov = 0.5 * (cov + cov.T)
    if not sample_node_offsets:  # append the node offsets' prior: mean 0, variance sb^2, uncorrelated
        mean = jnp.concatenate([mean, b_fixed])
        cov = jax.scipy.linalg.block_diag(cov, jnp.eye(n_b) * sb**2)
    return mean, cov, accept, jnp.max(rhat), burn1 + burn2 + n_draws, lap


class _Posterior(eqx.Module):
    """Log density (up to a constant) of the pair-level posterior of `posterior_mean` over
    theta = (free coordinates, common offset[, per-node offsets])."""

    template: Array  # (m, D) frame coordinates, fixed ones 0
    index: Array  # (F,) flat indices of the free coordinates in `template`
    node_offsets: Array  # (n,) zeros: the per-node offsets when they are not sampled
    observations: Observations
    numbers: _Numbers
    nu: Array
    scale: Array  # common scale of the Student-t pair errors [m]
    prior_precision: Array  # (P,) of the flat/Gaussian prior
    n_free: int = eqx.field(static=True)
    sample_node_offsets: bool = eqx.field(static=True)

    def errors(self, theta: Array) -> Array:
        f = self.n_free
        x = self.template.ravel().at[self.index].set(theta[:f]).reshape(self.template.shape)
        b = theta[f + 1 :] if self.sample_node_offsets else self.node_offsets
        return _errors(_State(x, theta[f], b), self.observations, self.numbers)

    def __call__(self, theta: Array) -> Array:
        e = self.errors(theta)
        ll = -0.5 * (self.nu + 1.0) * jnp.sum(self.observations.w * jnp.log1p((e / self.scale) ** 2 / self.nu))
        return ll - 0.5 * jnp.sum(self.prior_precision * theta * theta)


@eqx.filter_jit
def _posterior(free, template, mask, offset, node_offsets, observations, numbers, nu, sample_node_offsets: bool):
    """The posterior (`_Posterior`), its mode theta0 (the fit) and its Laplace covariance there (P, P): the
    inverse of J^T W J / s^2 + prior precision for a Gaussian likelihood of the same scale s."""
    f, n_b = free.shape[0], node_offsets.shape[0]
    theta0 = jnp.concatenate([free, jnp.reshape(offset, (1,))] + ([node_offsets] if sample_node_offsets else []))
    sc, sb = _prior_scales(numbers)
    prior = jnp.concatenate([jnp.zeros(f), jnp.stack([1.0 / sc**2]), jnp.full(n_b, 1.0 / sb**2)])[: theta0.shape[0]]
    target = _Posterior(
        template,
        jnp.nonzero(mask.ravel(), size=f)[0],
        jnp.zeros_like(node_offsets),
        observations,
        numbers,
        nu,
        jnp.asarray(1.0),
        prior,
        f,
        sample_node_offsets,
    )
    e0 = target.errors(theta0)
    n_par = f + numbers.use_c + numbers.use_b * n_b
    target = eqx.tree_at(lambda t: t.scale, target, _pair_scale(e0, observations.w > 0, n_par))
    jac = jax.jacfwd(target.errors)(theta0)
    info = (jac.T * observations.w) @ jac / target.scale**2 + jnp.diag(prior)
    return target, theta0, jnp.linalg.inv(info)


def _sqrt_cov(cov: Array) -> Array:
    """A square root R of a covariance (R R^T = cov), eigenvalues floored at 1e-12 of the largest."""
    lam, vec = jnp.linalg.eigh(0.5 * (cov + cov.T))
    return vec * jnp.sqrt(jnp.maximum(lam, 1e-12 * jnp.max(lam)))


def _kernel(name: str):
    """blackjax transition kernel `(key, state, logdensity, step_size, inverse_mass_matrix)`."""
    import blackjax  # here, not at the top: importing it (optax, ...) takes a second, and only sampling needs it

    if name == "nuts":
        return blackjax.nuts.build_kernel()
    hmc = blackjax.hmc.build_kernel()
    return lambda key, state, logp, step, inverse_mass: hmc(key, state, logp, step, inverse_mass, _LEAPFROG)


class _Chains(eqx.Module):
    """The chains in whitened coordinates theta = center + root @ u, with blackjax's adaptation states: dual
    averaging of the (shared) step size and Welford's estimate of the covariance of all chains' draws."""

    center: Array  # (P,)
    root: Array  # (P, P)
    states: Any  # blackjax HMCState of the C chains, positions u (C, P)
    step_size: Any  # blackjax DualAveragingAdaptationState
    draws: Any  # blackjax WelfordAlgorithmState over theta


def _whitened(target: _Posterior, center: Array, root: Array):
    return lambda u: target(center + root @ u)


def _chains_at(target: _Posterior, theta: Array, center: Array, cov: Array, step_size: Array) -> _Chains:
    """Chains at theta (C, P), whitened by cov around center, the step size adaptation started at step_size."""
    import blackjax
    from blackjax.adaptation.mass_matrix import welford_algorithm
    from blackjax.adaptation.step_size import dual_averaging_adaptation

    root = _sqrt_cov(cov)
    u = jnp.linalg.solve(root, (theta - center).T).T
    states = jax.vmap(lambda v: blackjax.hmc.init(v, _whitened(target, center, root)))(u)
    adaptation = dual_averaging_adaptation(target=_ACCEPT)[0](step_size)
    draws = welford_algorithm(is_diagonal_matrix=False)[0](center.shape[0])
    return _strong(_Chains(center, root, states, adaptation, draws))


def _strong(tree):
    """Every leaf a strongly typed array, so that `_run` sees the same types on every call (one compilation)."""
    return jax.tree.map(lambda x: jnp.asarray(x).astype(jnp.asarray(x).dtype), tree)


@eqx.filter_jit
def _start(target: _Posterior, theta0: Array, laplace: Array, key: Array, n_chains: int) -> _Chains:
    """Chains near the mode theta0 (0.1 Laplace sd), whitened by the Laplace covariance."""
    theta = theta0 + 0.1 * jax.random.normal(key, (n_chains, theta0.shape[0])) @ _sqrt_cov(laplace).T
    return _chains_at(target, theta, theta0, laplace, jnp.asarray(0.5 / theta0.shape[0] ** 0.25))


@eqx.filter_jit
def _rewhiten(target: _Posterior, chains: _Chains) -> _Chains:
    """The chains, unmoved, whitened by the mean and covariance of the draws pooled since the last whitening
    (a curved, weakly determined posterior is far from its Laplace approximation); the step size adaptation
    restarts from its average."""
    from blackjax.adaptation.mass_matrix import welford_algorithm

    cov, _, mean = welford_algorithm(is_diagonal_matrix=False)[2](chains.draws)
    cov = cov + jnp.diag(1e-12 + 1e-9 * jnp.diag(cov))
    theta = chains.center + chains.states.position @ chains.root.T
    return _chains_at(target, theta, mean, cov, jnp.exp(chains.step_size.log_step_size_avg))


@eqx.filter_jit
def _run(target: _Posterior, chains: _Chains, key: Array, adapt: Array, n: int, kernel: str):
    """n transitions of every chain (vmapped), the step size shared and jittered by +-20 % (no trajectory
    length resonates with the posterior). adapt (bool): the step size follows blackjax's dual averaging
    (towards a mean acceptance probability `_ACCEPT` of the chains) and the draws enter the Welford
    covariance; else the step size is the adaptation's average. Returns (chains, draws (C, n, P) of theta,
    summed acceptance probability per chain)."""
    from blackjax.adaptation.mass_matrix import welford_algorithm
    from blackjax.adaptation.step_size import dual_averaging_adaptation

    transition = _kernel(kernel)
    da_update = dual_averaging_adaptation(target=_ACCEPT)[1]
    wf_update = welford_algorithm(is_diagonal_matrix=False)[1]
    logp_u = _whitened(target, chains.center, chains.root)
    inverse_mass = jnp.ones(chains.center.shape[0])  # identity: the coordinates are whitened
    n_chains = chains.states.position.shape[0]

    def body(carry, k):
        states, da, wf = carry
        k_jitter, k_chains = jax.random.split(k)
        step = jnp.exp(jnp.where(adapt, da.log_step_size, da.log_step_size_avg))
        h = step * jax.random.uniform(k_jitter, minval=0.8, maxval=1.2)
        keys = jax.random.split(k_chains, n_chains)
        states, info = jax.vmap(lambda kk, s: transition(kk, s, logp_u, h, inverse_mass))(keys, states)
        theta = chains.center + states.position @ chains.root.T
        da_new = da_update(da, jnp.mean(info.acceptance_rate))
        da = jax.tree.map(lambda a, b: jnp.where(adapt, a, b), da_new, da)
        wf = jax.lax.cond(
            adapt, lambda w: jax.lax.fori_loop(0, n_chains, lambda c, w: wf_update(w, theta[c]), w), lambda w: w, wf
        )
        return (states, da, wf), (theta, info.acceptance_rate)

    (states, da, wf), (draws, acc) = jax.lax.scan(
        body, (chains.states, chains.step_size, chains.draws), jax.random.split(key, n)
    )
    chains = _strong(_Chains(chains.center, chains.root, states, da, wf))
    return chains, jnp.swapaxes(draws, 0, 1), jnp.sum(acc, axis=0)


def split_rhat(draws: np.ndarray) -> np.ndarray:
    """Split-chain potential scale reduction R-hat per coordinate of draws (C, n, K): blackjax's Gelman-Rubin
    statistic of the 2 C half chains (NumPy input: no compilation per number of draws)."""
    from blackjax.diagnostics import potential_scale_reduction

    half = draws.shape[1] // 2
    halves = np.concatenate([draws[:, :half], draws[:, half : 2 * half]], axis=0)
    return np.asarray(potential_scale_reduction(halves, chain_axis=0, sample_axis=1))


def _converged(draws: np.ndarray, mcse: float) -> bool:
    """The stopping rule: split R-hat below 1.01 and the Monte Carlo error of the mean, from the spread of
    the chains' means, below mcse posterior sd, in every coordinate of draws (C, n, K)."""
    err2 = np.var(np.mean(draws, axis=1), axis=0, ddof=1) / draws.shape[0]
    var = np.var(draws.reshape(-1, draws.shape[-1]), axis=0)
    return bool(np.max(split_rhat(draws)) < 1.01 and np.all(err2 <= mcse**2 * np.maximum(var, 1e-300)))


def _chunks(total: int, size: int) -> list[int]:
    return [size] * (total // size) + ([total % size] if total % size else [])


def _blackjax_posterior_mean(
    free,
    template,
    mask,
    offset,
    node_offsets,
    observations,
    numbers,
    key,
    nu,
    n_chains,
    n_steps,
    sample_node_offsets,
    mcse,
    kernel="hmc",
):
    target, theta0, laplace = _posterior(
        free, template, mask, offset, node_offsets, observations, numbers, nu, sample_node_offsets
    )
    f = free.shape[0]
    burn1 = min(n_steps // 8, _BURN)
    burn2 = min(n_steps // 4 - n_steps // 8, _BURN)
    n_blk = max(2 * ((n_steps - burn1 - burn2) // (2 * _BLOCK)), 2)
    block = (n_steps - burn1 - burn2) // n_blk
    k_start, k_burn1, k_burn2, k_run = jax.random.split(key, 4)
    chains = _start(target, theta0, laplace, k_start, n_chains)
    adapt = jnp.asarray(True)
    for phase, (burn, k_burn) in enumerate(((burn1, k_burn1), (burn2, k_burn2))):
        for c, n in enumerate(_chunks(burn, block)):  # chunks of the blocks' length: one compilation of `_run`
            chains, _, _ = _run(target, chains, jax.random.fold_in(k_burn, c), adapt, n, kernel)
        if phase == 0:
            chains = _rewhiten(target, chains)
    blocks, accepted = [], 0.0
    for k in range(n_blk):
        chains, draws, acc = _run(target, chains, jax.random.fold_in(k_run, k), ~adapt, block, kernel)
        blocks.append(np.asarray(draws))
        accepted += float(jnp.sum(acc))
        if mcse > 0 and k + 1 >= 4 and (k + 1) % 2 == 0 and _converged(np.concatenate(blocks, axis=1)[..., :f], mcse):
            break
    draws = np.concatenate(blocks, axis=1)
    flat = draws.reshape(-1, draws.shape[-1])
    mean = np.mean(flat, axis=0)
    cov = (flat - mean).T @ (flat - mean) / flat.shape[0]
    if not sample_node_offsets:  # append the node offsets' prior: mean 0, variance sb^2, uncorrelated
        sb = float(_prior_scales(numbers)[1])
        n_b = node_offsets.shape[0]
        mean = np.concatenate([mean, np.zeros(n_b)])
        cov = np.block([[cov, np.zeros((cov.shape[0], n_b))], [np.zeros((n_b, cov.shape[0])), np.eye(n_b) * sb**2]])
    accept = accepted / (draws.shape[1] * n_chains)
    rhat = float(np.max(split_rhat(draws[..., :f])))
    return mean, cov, accept, rhat, burn1 + burn2 + draws.shape[1], laplace


def posterior_mean(
    free: Array,
    template: Array,
    mask: Array,
    offset: Array,
    node_offsets: Array,
    observations: Observations,
    numbers: _Numbers,
    key: Array,
    nu: Array,
    n_chains: int,
    n_steps: int,
    sample_node_offsets: bool = True,
    mcse: float = 0.0,
    sampler: str = "blackjax",
):
    """Posterior mean and covariance of the free frame coordinates (and offsets) (`estimate=mean`).

    The least-squares / robust fit is the posterior *mode*. Where the geometry is weak (a direction the
    ranges pin down only to second order, e.g. nodes nearly in one plane or on one line), the posterior is
    curved and skewed, and its mode sits away from its mean; the mean is the estimate with the least
    expected squared error. Model: one observation per pair (`observations`, the per-pair median summary), each
    error Student-t with `nu` degrees of freedom and a common scale s = 1.4826 MAD(e) sqrt(M / (M - P)) of
    the fit's pair errors (per-pair systematic errors dominate on real meshes: repeated ranges of a pair
    are not independent, so the pair, not the single range, is the unit); flat prior on positions, the
    offsets' priors of `_prior_scales`.

    Sampled with blackjax: `n_chains` vmapped chains of HMC (`_LEAPFROG` leapfrog steps per transition) or
    NUTS, started near the fit in coordinates whitened by the Laplace covariance. A quarter of `n_steps` (at
    most 2 `_BURN`) is burn-in, in two phases that adapt one step size for all chains by blackjax's dual
    averaging (towards a mean acceptance probability of `_ACCEPT`; the step is jittered by +-20 % at every
    transition); blackjax's Welford estimator pools the first phase's draws of all chains, and their mean and
    covariance whiten the second phase and the sampling (a curved posterior is far from its Laplace
    approximation; one covariance from all chains' draws follows it better than blackjax's per-chain window
    adaptation did, docs/benchmarks/uncertainty.md). After the burn-in the chains run in blocks of `_BLOCK`
    transitions; split R-hat is blackjax's `potential_scale_reduction` of the half chains.

    Args:
        free: (F,) free coordinates of the fit; template: (m, D) frame coordinates (fixed ones 0);
        mask: (m, D) bool, which entries of `template` are free; offset, node_offsets: the fit's range offsets c and b;
        observations: pair observations (padding has weight 0); numbers: `_Numbers` of the fit; key: PRNG key;
        nu: Student-t degrees of freedom; n_chains, n_steps: sampler sizes.
        sample_node_offsets: False when the model has no per-node offsets (`numbers.use_b` off): they
            then enter no range, their posterior is their prior (mean 0, sd `node_bias_sigma_m`,
            independent of the rest), and they are returned as such instead of being sampled (P = F + 1
            sampled dimensions instead of F + 1 + n: the whitening costs O(P^2) per gradient).
        mcse: > 0: stop after the burn-in once the Monte Carlo error of the mean (from the spread of the
            chains' means) is below mcse posterior sd and split R-hat below 1.01 in every free coordinate,
            checked every two blocks (at least four); 0: run all n_steps.
        sampler: `blackjax` (HMC), `blackjax-nuts` (NUTS) or `jaxcal` (the hand-written HMC).

    Returns:
        (mean (F + 1 + n,), covariance (F + 1 + n, F + 1 + n), acceptance rate, max split R-hat over the
        free coordinates, transitions run per chain (burn-in included), the Laplace covariance of the same
        model with a Gaussian likelihood of the same scale, (J^T W J / s^2 + prior)^-1 at the fit (P, P):
        the linearisation that `solve` compares the samples with).
    """
    args = (free, template, mask, offset, node_offsets, observations, numbers, key, nu, n_chains, n_steps)
    if sampler == "jaxcal":
        return _own_posterior_mean(*args, sample_node_offsets, mcse)
    return _blackjax_posterior_mean(*args, sample_node_offsets, mcse, "nuts" if sampler == "blackjax-nuts" else "hmc")


def posterior_defect(
    i: np.ndarray,
    j: np.ndarray,
    n_nodes: int,
    dim: int,
    nu: float,
    n_offsets: int,
    node_ids: tuple[str, ...],
    seed: int = 0,
) -> str:
    """Why the pair-level posterior of `estimate=mean` cannot be sampled, from the measurement graph
    alone ("" when it can). Decided before sampling, so the fallback does not hang on a chain's path.

    Two structural defects:
    - a node with k distinct neighbours has, far from them, a likelihood that decays like
      r^(-k (nu + 1)) (Student-t tails) over a volume growing like r^(dim - 1): with k (nu + 1) <= dim
      the posterior (flat prior) is improper: its mean and covariance do not exist.
    - the pairs do not fix the configuration to first order: the rigidity matrix (one row per measured
      pair, d||x_i - x_j|| / dx at a random generic configuration) has rank below
      dim n - dim (dim + 1) / 2 (generic rigidity), or there are fewer pairs than unknowns (positions and
      offsets); the posterior then spreads along a continuum and its mean is no estimate.

    Args:
        i, j: (M,) node indices (0..n_nodes-1) of the measured unordered pairs (no duplicates needed).
        n_nodes: number of (connected) nodes; dim: 2 or 3; nu: Student-t degrees of freedom;
        n_offsets: fitted range offsets (common and per-node) that the pairs must also fix;
        node_ids: ids of the n_nodes nodes (for the message); seed: of the random configuration.

    Returns:
        A one-line reason, or "".
    """
    pairs = {
        (min(a, b), max(a, b)) for a, b in zip(np.asarray(i).tolist(), np.asarray(j).tolist(), strict=False) if a != b
    }
    nbrs: list[set[int]] = [set() for _ in range(n_nodes)]
    for a, b in pairs:
        nbrs[a].add(b)
        nbrs[b].add(a)
    for k in range(n_nodes):
        if len(nbrs[k]) * (nu + 1.0) <= dim:
            names = ", ".join(node_ids[q] for q in sorted(nbrs[k]))
            return (
                f"{node_ids[k]} ranges only {names}: its posterior under the Student-t likelihood "
                f"(nu={nu:g}) is improper"
            )
    n_unknown = dim * n_nodes - dim * (dim + 1) // 2
    if len(pairs) < n_unknown + n_offsets:
        return f"{len(pairs)} measured pairs for {n_unknown + n_offsets} unknowns"
    x = np.random.default_rng(seed).normal(size=(n_nodes, dim))
    rig = np.zeros((len(pairs), n_nodes * dim))
    for row, (a, b) in enumerate(sorted(pairs)):
        u = (x[a] - x[b]) / np.linalg.norm(x[a] - x[b])
        rig[row, a * dim : (a + 1) * dim] = u
        rig[row, b * dim : (b + 1) * dim] = -u
    if np.linalg.matrix_rank(rig) < n_unknown:
        return "the measured pairs do not make the network rigid (it can flex without changing a range)"
    return ""
