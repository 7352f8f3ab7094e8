"""Gaussian-process primitives shared by the trajectory GP methods (`gp`, `gp_anchor`).

The Matern kernel (any nu; closed forms for 1/2, 3/2, 5/2, a series for the rest), the GP
hyperparameters, the negative log marginal likelihood of a zero-mean GP with white noise, the range
targets (`range`, `inv-log`) and the stratified training subsample. `gp` and `gp_anchor` both build on
this module, so neither imports the other's internals (no import circle).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float

from jaxcal import solver as S
from jaxcal.errors import JaxcalError

__all__ = [
    "matern",
    "Hyper",
    "neg_log_marginal_likelihood",
    "to_target",
    "from_target",
    "stratified_subsample",
    "hyper_penalty",
    "laplace_fit",
    "laplace_covariance",
]


# ---------------------------------------------------------------------------------------- kernel

_Z_SWITCH = 9.0
_N_SERIES = 48


def _matern_general(z2, nu: float):
    """2^(1-nu)/Gamma(nu) z^nu K_nu(z) as a function of z^2, for non-integer nu (see module doc)."""
    c = 2.0 ** (1.0 - nu) / math.gamma(nu)
    pref = math.pi / (2.0 * math.sin(nu * math.pi))
    small = z2 <= _Z_SWITCH**2
    x = jnp.where(small, z2, 0.0) / 4.0
    # sum_k x^k / (k! Gamma(k + 1 -+ nu)) by Horner on precomputed coefficients
    a1 = [1.0 / (math.factorial(k) * math.gamma(k + 1 - nu)) for k in range(_N_SERIES)]
    a2 = [1.0 / (math.factorial(k) * math.gamma(k + 1 + nu)) for k in range(_N_SERIES)]
    s1 = jnp.zeros_like(x)
    s2 = jnp.zeros_like(x)
    for k in range(_N_SERIES - 1, -1, -1):
        s1 = s1 * x + a1[k]
        s2 = s2 * x + a2[k]
    z2s = jnp.where(small, z2, 1.0)
    zpow = jnp.where(small & (z2 > 0), jnp.exp(nu * jnp.log(jnp.where(z2 > 0, z2s, 1.0))), 0.0)
    f_small = c * pref * (2.0**nu * s1 - 2.0 ** (-nu) * zpow * s2)
    # asymptotic K_nu(z) ~ sqrt(pi / 2z) e^-z (1 + (mu-1)/8z + (mu-1)(mu-9)/(2!(8z)^2) + ...)
    zl = jnp.sqrt(jnp.where(small, _Z_SWITCH**2, z2))
    mu = 4.0 * nu * nu
    term = jnp.ones_like(zl)
    series = jnp.ones_like(zl)
    for k in range(1, 8):
        term = term * (mu - (2 * k - 1) ** 2) / (k * 8.0 * zl)
        series = series + term
    f_large = c * zl**nu * jnp.sqrt(math.pi / (2.0 * zl)) * jnp.exp(-zl) * series
    return jnp.where(small, f_small, f_large)


def matern(d2: Float[Array, ...], length: Float[Array, ""], variance: Float[Array, ""], nu: float):
    """Matern covariance from squared distances.

    Args:
        d2: squared distances [m^2], any shape. length: length scale l [m]. variance: s^2.
        nu: smoothness (static): 0.5, 1.5, 2.5 in closed form, other non-integer values general.

    Returns:
        k(r) = s^2 2^(1-nu)/Gamma(nu) z^nu K_nu(z), z = sqrt(2 nu) r / l, same shape as d2.
    """
    z2 = 2.0 * nu * d2 / length**2
    if nu in (0.5, 1.5, 2.5):
        safe = jnp.where(z2 > 0, z2, 1.0)
        z = jnp.where(z2 > 0, jnp.sqrt(safe), 0.0)
        poly = 1.0 if nu == 0.5 else (1.0 + z if nu == 1.5 else 1.0 + z + z2 / 3.0)
        return variance * poly * jnp.exp(-z)
    if float(nu).is_integer() or nu <= 0:
        raise JaxcalError(f"parameter nu: need a positive non-integer smoothness, got {nu}")
    return variance * _matern_general(z2, nu)


def _sqdist(a, b):
    return jnp.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=-1)


def _cone(x, anchor):
    d2 = jnp.sum((x - anchor) ** 2, axis=-1)
    safe = jnp.where(d2 > 0, d2, 1.0)
    return jnp.where(d2 > 0, jnp.sqrt(safe), 0.0)


# ------------------------------------------------------------------------------------ likelihood


class Hyper(eqx.Module):
    """GP hyperparameters in log space (one anchor, or stacked over anchors).

    Attributes:
        log_length: log length scale [log m]. log_variance: log signal variance.
        log_noise: log white-noise variance.
    """

    log_length: Float[Array, ...]
    log_variance: Float[Array, ...]
    log_noise: Float[Array, ...]


def _gram(h: Hyper, x, mask, nu, jitter, noise_scale=None):
    m = mask.astype(x.dtype)
    var = jnp.exp(h.log_variance)
    k = matern(_sqdist(x, x), jnp.exp(h.log_length), var, nu)
    k = k * m[:, None] * m[None, :]
    noise = jnp.exp(h.log_noise) * (1.0 if noise_scale is None else noise_scale)
    diag = (noise + jitter * var) * m + (1.0 - m)  # padding: unit diagonal, no coupling
    return k + jnp.diag(diag)


def hyper_penalty(h: Hyper, log_max_length, log_min_variance, log_min_length=None, log_max_variance=None):
    """Soft bounds on the kernel: 0.5 (x / 0.25)^2 for x the excess of log l over `log_max_length`, of
    `log_min_variance` over log s^2 and (when given) of `log_min_length` over log l and of log s^2 over
    `log_max_variance` (0 inside the bounds).

    Where the ranges show no spatially correlated error the marginal likelihood is largest at s^2 = 0
    (f vanishes: the GP is `nls` on the subsample) and flat along log s^2 -> -inf and then along log l:
    BFGS walked there for 5 of the 10 campus anchors (s = 1e-5 m, l = 1e9-1e12 m, more than 100 steps,
    then the 4x retry of `jaxcal.solver.retry_unconverged`). The floor on s^2 (far below the residual
    variance, so f stays negligible) and the ceiling on l (beyond the data a Matern f is a constant
    plus a trend, which trade with b and the anchor) end those walks. The floor on l is the shortest
    length scale a truncated basis resolves, the ceiling on s^2 keeps f a part of the residual (`gp_space`).
    """
    over = jnp.maximum(h.log_length - log_max_length, 0.0)
    under = jnp.maximum(log_min_variance - h.log_variance, 0.0)
    out = 0.5 * (over / 0.25) ** 2 + 0.5 * (under / 0.25) ** 2
    if log_min_length is not None:
        out = out + 0.5 * (jnp.maximum(log_min_length - h.log_length, 0.0) / 0.25) ** 2
    if log_max_variance is not None:
        out = out + 0.5 * (jnp.maximum(h.log_variance - log_max_variance, 0.0) / 0.25) ** 2
    return out


def laplace_fit(nlml, init, n, max_steps: int):
    """Minimise `nlml(theta)` (a pytree whose first leaf is the anchor (3,)) by BFGS, and the anchor block
    of the inverse Hessian of `nlml` at the optimum (the Laplace / GLS covariance, every parameter
    marginalised). `n` (valid ranges) scales the objective so the tolerances mean the same for any n.

    Returns:
        (theta (init where the optimum is not finite), covariance (3, 3), outcome code).
    """
    sol: optx.Solution = optx.minimise(
        lambda th, _: nlml(th) / n, optx.BFGS(rtol=1e-7, atol=1e-7), init, max_steps=max_steps, throw=False
    )
    ok = jnp.isfinite(nlml(sol.value))
    th = jax.tree.map(lambda a, b: jnp.where(ok, a, b), sol.value, init)
    return th, laplace_covariance(nlml, th), S.outcome(sol)


def laplace_covariance(nlml, th):
    """The anchor block (3, 3) of the inverse Hessian of `nlml` at `th` (a pytree whose first leaf is the
    anchor): the Laplace / GLS covariance, every other parameter marginalised."""
    flat, unravel = jax.flatten_util.ravel_pytree(th)
    hess = jax.hessian(lambda v: nlml(unravel(v)))(flat)
    ev, vec = jnp.linalg.eigh(0.5 * (hess + hess.T))
    # A saddle or flat direction (not a minimum) gets a large, not a negative, variance.
    ev = jnp.maximum(jnp.abs(ev), 1e-10 * jnp.max(jnp.abs(ev)))
    cov = (vec / ev) @ vec.T
    return cov[:3, :3]


def neg_log_marginal_likelihood(
    h: Hyper,
    x: Float[Array, "n 3"],
    y: Float[Array, " n"],
    mask: Bool[Array, " n"],
    nu: float = 1.5,
    jitter: float = 1e-6,
    noise_scale: Float[Array, " n"] | None = None,
) -> Float[Array, ""]:
    """-log p(y | x, h): zero-mean GP, Matern + white noise; padded entries (mask False) ignored.

    Args:
        h: hyperparameters. x: (n, 3) inputs [m]. y: (n,) centred targets. mask: (n,) valid entries.
        nu: Matern smoothness (static). jitter: diagonal jitter relative to the signal variance.
        noise_scale: (n,) multiplies the white-noise variance per entry (None: 1 everywhere).
    """
    k = _gram(h, x, mask, nu, jitter, noise_scale)
    chol = jnp.linalg.cholesky(k)
    yy = jnp.where(mask, y, 0.0)
    alpha = jax.scipy.linalg.cho_solve((chol, True), yy)
    n = jnp.sum(mask)
    return 0.5 * yy @ alpha + jnp.sum(jnp.log(jnp.diagonal(chol))) + 0.5 * n * jnp.log(2.0 * jnp.pi)


# ---------------------------------------------------------------------------------------- target


def to_target(r, target: str):
    """Range [m] -> GP target (`range`: identity; `inv-log`: 1 / log10(sqrt(r) + 1), r >= 1 mm)."""
    if target == "range":
        return r
    return 1.0 / jnp.log10(jnp.sqrt(jnp.maximum(r, 1e-3)) + 1.0)


def from_target(y, target: str):
    """Inverse of `to_target` (targets <= 0 of `inv-log` map to +inf)."""
    if target == "range":
        return y
    safe = jnp.where(y > 0, y, 1.0)
    return jnp.where(y > 0, (10.0 ** (1.0 / safe) - 1.0) ** 2, jnp.inf)


# ---------------------------------------------------------------------------------------- subsample


def stratified_subsample(rng_m: np.ndarray, n_train: int, n_bins: int, seed: int) -> np.ndarray:
    """Indices of at most `n_train` ranges, equal quotas from `n_bins` equal-width range strata.

    Strata with fewer ranges than their quota give all of theirs; the remaining quota is filled at
    random from the rest. Host-side NumPy (once per dataset). Returns sorted indices.
    """
    n = rng_m.size
    if n <= n_train:
        return np.arange(n)
    gen = np.random.default_rng(seed)
    edges = np.linspace(rng_m.min(), rng_m.max(), n_bins + 1)
    b = np.clip(np.searchsorted(edges, rng_m, side="right") - 1, 0, n_bins - 1)
    quota = n_train // n_bins
    per_bin = []
    for k in range(n_bins):
        idx = np.nonzero(b == k)[0]
        per_bin.append(idx if idx.size <= quota else gen.choice(idx, quota, replace=False))
    chosen = np.concatenate(per_bin)
    rest = np.setdiff1d(np.arange(n), chosen)
    extra = gen.choice(rest, n_train - chosen.size, replace=False)
    return np.sort(np.concatenate([chosen, extra]))
