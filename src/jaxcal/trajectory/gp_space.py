"""The GP as the noise model of every range, over space (`gp` with `model=space`).

Model per anchor, every range:

    r_t = |p_t - a| + b + f(x_t) + e_t,

x_t the tag's horizontal position (east, north) [m], f ~ GP(0, Matern nu) over the plane: a range error that
repeats where the route repeats (a wall, the antenna's pattern seen from the same place, a route driven in
laps), unlike `model=path` (`gp_path`), whose f is correlated along the distance driven and so counts each
lap as new information. e_t is white noise of variance s_n^2 / w_t with w_t the Cauchy weight of the `nls`
residual (heavy tail, as `model=path`). The anchor a, the bias b and the kernel (l, s_f^2, s_n^2) maximise
the marginal likelihood (Optimistix BFGS, seeded at `nls`): generalised least squares for (a, b) under the
fitted spatial covariance.

Every range is used through a Hilbert-space (Laplacian eigenfunction) approximation of f (Solin & Sarkka
2020): on the rectangle [-L_1, L_1] x [-L_2, L_2] around the anchor's positions (their half extent times
`basis_margin`), f(x) = sum_j phi_j(x) w_j with phi_j the products of sines
L_d^-1/2 sin(pi j_d (x_d + L_d) / (2 L_d)), j_d = 1..`n_basis`, and w_j ~ N(0, S(sqrt(lambda_j))), S the
Matern spectral density in 2-D and lambda_j the Laplacian's eigenvalues. Then the ranges' covariance is
Phi Lambda Phi^T + s_n^2 W^-1 and the Woodbury identity gives the likelihood from m x m matrices
(m = n_basis^2): G = Phi^T W Phi is fixed by the data and computed once (O(n m^2)), every evaluation is
O(n m + m^3) (`basis_nlml`). Hand-written (50 lines) rather than tinygp: tinygp has no Hilbert-space basis
(its fast solvers are 1-D quasiseparable kernels) and is not a dependency; `basis_nlml` is tested against
the dense covariance of the same basis with a SciPy Cholesky, and the basis against the dense Matern
kernel as `n_basis` grows (tests/test_gp_space.py).

The basis resolves length scales down to about 3.42 L / n_basis (Riutort-Mayol et al. 2023, Matern-3/2:
m >= 3.42 c S / l); the length scale has a soft floor there (`hyper_penalty`): a shorter error is left to the
white noise. The ceiling is `max_length` x the radius of the positions, as for `model=path`: a smooth f
over the whole route is a trend that trades with the anchor's cone. The signal variance has a soft
ceiling too, `max_signal` x the variance of the (Cauchy-weighted) `nls` residuals: f is a part of that
residual; unbounded, on hanyang LOS the fit let f take the cone (s_f = 4-14 m, every anchor 2 m off and
caught by the fallback). On a flat path the height is not fitted (held at `nls`'s): f over the plane
would trade with it. That trade is what the GLS
covariance (inverse Hessian of the negative log marginal likelihood, the kernel included) holds; it is
then widened to the `nls` covariance in every direction where it is smaller, and the fallback, flat-path
and reporting rules are `model=path`'s (`gp_path.calibrate_every_range`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from jaxcal.data import Result
from jaxcal.trajectory.gp_kernel import Hyper, _cone, hyper_penalty, laplace_fit

__all__ = ["basis_index", "eigenfunctions", "spectral_density", "basis_nlml", "fit_space_all", "calibrate_space"]

# basis resolution of a Matern-3/2 GP (Riutort-Mayol et al. 2023): n_basis >= 3.42 L / l per axis
_RESOLUTION = 3.42


def basis_index(n_basis: int) -> np.ndarray:
    """(n_basis^2, 2) integer frequencies (j_1, j_2), each 1..n_basis."""
    j = np.arange(1, n_basis + 1)
    return np.stack(np.meshgrid(j, j, indexing="ij"), axis=-1).reshape(-1, 2)


def eigenfunctions(x: Float[Array, "n 2"], half: Float[Array, " 2"], idx) -> Float[Array, "n m"]:
    """Laplacian eigenfunctions on [-L_1, L_1] x [-L_2, L_2] (Dirichlet) at x (n, 2): prod_d L_d^-1/2
    sin(pi j_d (x_d + L_d) / (2 L_d)) for the frequencies idx (m, 2)."""
    arg = jnp.pi * jnp.asarray(idx, x.dtype)[None] * (x[:, None, :] + half) / (2.0 * half)
    return jnp.prod(jnp.sin(arg) / jnp.sqrt(half), axis=-1)


def spectral_density(omega2, length, variance, nu: float, dim: int = 2):
    """Spectral density S(omega) of the Matern nu kernel in `dim` dimensions at omega^2 [1/m^2]:
    s^2 2^d pi^(d/2) Gamma(nu + d/2) (2 nu)^nu / (Gamma(nu) l^(2 nu)) (2 nu / l^2 + omega^2)^-(nu + d/2)."""
    c = dim * math.log(2.0) + 0.5 * dim * math.log(math.pi) + math.lgamma(nu + 0.5 * dim) - math.lgamma(nu)
    c += nu * math.log(2.0 * nu)
    log_s = c - 2.0 * nu * jnp.log(length) - (nu + 0.5 * dim) * jnp.log(2.0 * nu / length**2 + omega2)
    return variance * jnp.exp(log_s)


def basis_nlml(h: Hyper, phi, gram, omega2, y, weight, nu: float) -> Float[Array, ""]:
    """-log N(y; 0, Phi Lambda Phi^T + s_n^2 W^-1) by Woodbury, from m x m matrices.

    Args:
        h: log length scale [log m], log signal variance, log noise variance. phi: (n, m) eigenfunctions.
        gram: (m, m) Phi^T W Phi. omega2: (m,) Laplacian eigenvalues [1/m^2]. y: (n,) targets.
        weight: (n,) W, the inverse white-noise variance multipliers (0: padding, skipped). nu: static.
    """
    sn2 = jnp.exp(h.log_noise)
    sl = jnp.sqrt(spectral_density(omega2, jnp.exp(h.log_length), jnp.exp(h.log_variance), nu))
    m = omega2.shape[0]
    # symmetric by construction; jnp.linalg.cholesky's symmetrisation cost 4x the factorisation on this CPU
    b = jnp.eye(m, dtype=y.dtype) + sl[:, None] * gram * sl[None, :] / sn2
    chol = jax.lax.linalg.cholesky(b, symmetrize_input=False)
    u = sl * (phi.T @ (weight * y)) / sn2
    v = jax.scipy.linalg.solve_triangular(chol, u, lower=True)
    valid = weight > 0
    n = jnp.sum(valid)
    quad = jnp.sum(weight * y * y) / sn2 - jnp.sum(v * v)
    logdet = n * jnp.log(sn2) - jnp.sum(jnp.where(valid, jnp.log(jnp.where(valid, weight, 1.0)), 0.0))
    logdet = logdet + 2.0 * jnp.sum(jnp.log(jnp.diag(chol)))
    return 0.5 * (quad + logdet + n * jnp.log(2.0 * jnp.pi))


class SpaceModel(eqx.Module):
    """Anchor (3,) [m], range bias [m] and the spatial kernel's log hyperparameters."""

    anchor: Float[Array, ...]
    bias: Float[Array, ...]
    hyper: Hyper


def domain(x: Float[Array, "n 2"], mask: Bool[Array, " n"], margin: float):
    """(centre (2,), half sizes L (2,)) of the basis rectangle: the positions' box, its half extent x
    `margin` (at least 1 m)."""
    lo = jnp.min(jnp.where(mask[:, None], x, jnp.inf), axis=0)
    hi = jnp.max(jnp.where(mask[:, None], x, -jnp.inf), axis=0)
    return 0.5 * (lo + hi), jnp.maximum(0.5 * (hi - lo) * margin, 1.0)


@eqx.filter_jit
def fit_space_all(
    x, r, mask, noise_scale, a0, b0, free_z, nu: float, max_steps: int, min_signal: float, max_length: float,
    max_signal: float, n_basis: int, margin: float,
):  # fmt: skip
    """Every anchor (`lax.map`): x (A, n, 3), r / mask / noise_scale (A, n), seeds a0 (A, 3), b0 (A,),
    free_z (A,) whether the anchor's height is fitted (False: a flat path, the height stays a0's).

    Returns:
        (anchor (A, 3), covariance (A, 3, 3), bias (A,), hyperparameters, outcome codes (A,)).
    """
    idx = basis_index(n_basis)

    def one(x, r, m, s, a0, b0, fz):
        nv = jnp.maximum(jnp.sum(m), 1)
        centre, half = domain(x[:, :2], m, margin)
        origin = jnp.concatenate([centre, (jnp.sum(jnp.where(m, x[:, 2], 0.0)) / nv)[None]])
        xc = jnp.where(m[:, None], x - origin, 0.0)
        weight = jnp.where(m, 1.0 / s, 0.0)
        phi = eigenfunctions(xc[:, :2], half, idx)
        gram = phi.T @ (weight[:, None] * phi)
        omega2 = jnp.sum((jnp.pi * idx / (2.0 * half)) ** 2, axis=-1)
        res = jnp.where(m, r - _cone(xc, a0 - origin) - b0, 0.0)
        var = jnp.maximum(jnp.sum(weight * res**2) / nv, 1e-6)
        radius = jnp.max(jnp.where(m, jnp.linalg.norm(xc[:, :2], axis=-1), 0.0))
        l_min = _RESOLUTION * jnp.max(half) / n_basis
        l_max = jnp.maximum(max_length * radius, 2.0 * l_min)
        init = SpaceModel(
            a0 - origin, b0, Hyper(jnp.log(jnp.sqrt(l_min * l_max)), jnp.log(0.5 * var), jnp.log(0.5 * var))
        )
        bounds = (jnp.log(l_max), jnp.log(min_signal * var), jnp.log(l_min), jnp.log(max_signal * var))
        z0 = a0[2] - origin[2]

        def nlml(th):
            anchor = th.anchor.at[2].set(jnp.where(fz, th.anchor[2], z0))
            y = jnp.where(m, r - _cone(xc, anchor) - th.bias, 0.0)
            # the penalty per range: the likelihood of 1e4-1e5 ranges would overrule a fixed one
            return basis_nlml(th.hyper, phi, gram, omega2, y, weight, nu) + nv * hyper_penalty(th.hyper, *bounds)

        th, cov, code = laplace_fit(nlml, init, nv, max_steps)
        return th.anchor + origin, cov, th.bias, th.hyper, code

    # lax.map, not vmap: one anchor's basis (n x m) in memory at a time, and batched Cholesky
    # gradients are slow on CPU
    return jax.lax.map(lambda a: one(*a), (x, r, mask, noise_scale, a0, b0, free_z))


def calibrate_space(dataset, p, groups, info, planar) -> Result:
    """`gp` with `model=space` (module doc): `nls` start and Cauchy weights, the spatial GP on every range."""
    from jaxcal.trajectory.gp_path import calibrate_every_range

    free_z = jnp.asarray(~np.asarray(planar, dtype=bool))

    def fit(args, steps):
        return fit_space_all(
            *args, free_z, p.nu, steps, p.min_signal, p.max_length, p.max_signal, p.n_basis, p.basis_margin
        )

    return calibrate_every_range(dataset, p, groups, info, planar, "space", fit)
