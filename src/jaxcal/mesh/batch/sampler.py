"""`estimate=mean`: the pair-level posterior of the positions, sampled by blackjax's Hamiltonian Monte Carlo
(`posterior_mean`), and the graph checks that decide before any sampling whether it can be sampled
(`posterior_defect`).

The kernels (HMC with `_LEAPFROG` leapfrog steps, or NUTS), the step-size rule (dual averaging), the
covariance estimate of the burn-in draws (Welford) and R-hat (`potential_scale_reduction`) are blackjax's.
jaxcal adds the schedule: one step size and one whitening for all chains, the whitening estimated from the
burn-in draws of all chains pooled (blackjax's `window_adaptation` adapts each chain on its own draws, which
needed 2.8x the transitions on the weak-geometry recordings, docs/benchmarks/index.md "Batch sampler"), and
the stopping rule on the Monte Carlo error of the mean.
"""

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


def _pair_scale(e: Array, real: Array, n_par: Array) -> Array:
    """Robust scale [m] of pair errors: 1.4826 MAD, inflated for the fitted parameters (sqrt(M / (M - P)))."""
    m = jnp.sum(real)
    mad = jnp.nanmedian(jnp.where(real, jnp.abs(e), jnp.nan))
    return jnp.maximum(1.4826 * mad * jnp.sqrt(m / jnp.maximum(m - n_par, 1.0)), 1e-6)


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


def _split_rhat(draws: np.ndarray) -> np.ndarray:
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
    return bool(np.max(_split_rhat(draws)) < 1.01 and np.all(err2 <= mcse**2 * np.maximum(var, 1e-300)))


def _chunks(total: int, size: int) -> list[int]:
    return [size] * (total // size) + ([total % size] if total % size else [])


def _sample(
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
    kernel,
):
    """`posterior_mean` with blackjax `kernel` (`hmc` or `nuts`)."""
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
    rhat = float(np.max(_split_rhat(draws[..., :f])))
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
    sampler: str = "hmc",
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
        sampler: `hmc` or `nuts` (blackjax's kernels).

    Returns:
        (mean (F + 1 + n,), covariance (F + 1 + n, F + 1 + n), acceptance rate, max split R-hat over the
        free coordinates, transitions run per chain (burn-in included), the Laplace covariance of the same
        model with a Gaussian likelihood of the same scale, (J^T W J / s^2 + prior)^-1 at the fit (P, P):
        the linearisation that `solve` compares the samples with).
    """
    args = (free, template, mask, offset, node_offsets, observations, numbers, key, nu, n_chains, n_steps)
    return _sample(*args, sample_node_offsets, mcse, sampler)


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
