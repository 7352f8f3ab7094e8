"""The GP as the noise model of every range, over space (`gp` with `model=space`).

Model per anchor, every range:

    r_t = |p_t - a| + b + f(x_t) + e_t,

x_t the tag's horizontal position (east, north) [m], f ~ GP(0, Matern nu) over the plane: a range error that
repeats where the route repeats (a wall, the antenna's pattern seen from the same place, a route driven in
laps), unlike `model=path` (`gp_path`), whose f is correlated along the distance driven and so counts each
lap as new information. e_t is white noise of variance s_n^2 / w_t with w_t the Cauchy weight of the `nls`
residual (heavy tail, as `model=path`). The anchor a, the bias b and the kernel (l, s_f^2, s_n^2) maximise
the marginal likelihood, seeded at `nls`: generalised least squares for (a, b) under the fitted spatial
covariance.

How the optimum is found (`fit_space_all`; same optimum as a joint BFGS over all seven parameters, tested
against SciPy on the dense objective, about 5x less CPU): the cone is linearised about the current (a, b),
y = y0 - J delta, so the (a, b) step is a GLS solve in closed form for any kernel; the length scale is
searched in 1-D (a 12-point grid over log l, then golden section), each value with one eigendecomposition
D^1/2 G D^1/2 = U E U^T that makes the remaining 2-D BFGS over (s_f^2, s_n^2) O(m) per step; then the cone
is relinearised at the new (a, b) and l searched near its last value, until (a, b) move less than 10 um
(2-5 linearisations). A fixed point of that loop is a stationary point of the exact likelihood (the linear
model matches its value and gradient there). The covariance is the Hessian of the exact likelihood there.

Every range is used through a Hilbert-space (Laplacian eigenfunction) approximation of f (Solin & Sarkka
2020): on the rectangle [-L_1, L_1] x [-L_2, L_2] around the anchor's positions (their half extent times
`basis_margin`), f(x) = sum_j phi_j(x) w_j with phi_j the products of sines
L_d^-1/2 sin(pi j_d (x_d + L_d) / (2 L_d)), j_d = 1..`n_basis`, and w_j ~ N(0, S(sqrt(lambda_j))), S the
Matern spectral density in 2-D and lambda_j the Laplacian's eigenvalues. Then the ranges' covariance is
Phi Lambda Phi^T + s_n^2 W^-1 and the Woodbury identity gives the likelihood from m x m matrices
(m = n_basis^2): G = Phi^T W Phi is fixed by the data and computed once, in O(n n_basis^2) by the
product-to-sum identity of the sines (`basis_gram`), and Phi^T v as s_1^T diag(v) s_2 from the per-axis sine
factors (`project`), never forming the (n, m) matrix Phi. Hand-written rather than tinygp: tinygp has no
Hilbert-space basis (its fast solvers are 1-D quasiseparable kernels) and is not a dependency; `basis_nlml`
is tested against the dense covariance of the same basis with a SciPy Cholesky, `basis_gram` and `project`
against Phi, and the basis against the dense Matern kernel as `n_basis` grows (tests/test_gp_space.py).

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
import optimistix as optx
from jaxtyping import Array, Bool, Float

from jaxcal import solver as S
from jaxcal.data import Result
from jaxcal.trajectory.gp_kernel import Hyper, _cone, hyper_penalty, laplace_covariance

__all__ = ["basis_index", "eigenfunctions", "spectral_density", "basis_nlml", "fit_space_all", "calibrate_space"]

# basis resolution of a Matern-3/2 GP (Riutort-Mayol et al. 2023): n_basis >= 3.42 L / l per axis
_RESOLUTION = 3.42
# the length-scale search: log l over [log l_min - margin, log l_max + margin] (the soft bounds' penalty is
# nv x 0.5 (x / 0.25)^2 outside), a grid then golden-section steps; later linearisations search +- _LOCAL
_SEARCH_MARGIN, _N_GRID, _N_GOLDEN, _LOCAL = 0.5, 12, 18, 0.25
# relinearise until the anchor and bias move less than this [m]
_STEP_TOL = 1e-5
# eigenvalues below this x the largest are directions without data; log s_f^2, log s_n^2 are kept inside
# [log(min_signal var) - _BOX, log(max_signal var) + _BOX] in the likelihood
_EIG_FLOOR, _BOX = 1e-12, 5.0


def basis_index(n_basis: int) -> np.ndarray:
    """(n_basis^2, 2) integer frequencies (j_1, j_2), each 1..n_basis."""
    j = np.arange(1, n_basis + 1)
    return np.stack(np.meshgrid(j, j, indexing="ij"), axis=-1).reshape(-1, 2)


def eigenfunctions(x: Float[Array, "n 2"], half: Float[Array, " 2"], idx) -> Float[Array, "n m"]:
    """Laplacian eigenfunctions on [-L_1, L_1] x [-L_2, L_2] (Dirichlet) at x (n, 2): prod_d L_d^-1/2
    sin(pi j_d (x_d + L_d) / (2 L_d)) for the frequencies idx (m, 2)."""
    arg = jnp.pi * jnp.asarray(idx, x.dtype)[None] * (x[:, None, :] + half) / (2.0 * half)
    return jnp.prod(jnp.sin(arg) / jnp.sqrt(half), axis=-1)


def sine_factors(x: Float[Array, "n 2"], half: Float[Array, " 2"], n_basis: int):
    """Per axis d the (n, n_basis) factors L_d^-1/2 sin(j pi (x_d + L_d) / (2 L_d)), j = 1..n_basis, whose
    products are the eigenfunctions: phi_(j1, j2)(x) = s_1[j1](x) s_2[j2](x) (the order of `basis_index`)."""
    j = jnp.arange(1, n_basis + 1, dtype=x.dtype)
    theta = jnp.pi * (x + half) / (2.0 * half)
    return tuple(jnp.sin(theta[:, d, None] * j) / jnp.sqrt(half[d]) for d in range(2))


def project(factors, v: Float[Array, "n c"]) -> Float[Array, "m c"]:
    """Phi^T v for the (n, c) columns v, as s_1^T diag(v) s_2 per column: (n_basis^2, c), O(n m c) in GEMMs,
    without the (n, m) matrix Phi."""
    s1, s2 = factors
    out = jax.vmap(lambda c: (s1.T @ (c[:, None] * s2)).reshape(-1), in_axes=1, out_axes=1)(v)
    return out


def basis_gram(x: Float[Array, "n 2"], weight: Float[Array, " n"], half: Float[Array, " 2"], n_basis: int):
    """G = Phi^T W Phi (m, m) in O(n n_basis^2) instead of O(n m^2): sin(j t) sin(k t) =
    (cos((j - k) t) - cos((j + k) t)) / 2 per axis, so every entry is a signed sum of four entries of
    C[p, q] = sum_t w_t cos(p t_1) cos(q t_2), p, q = 0..2 n_basis (exact up to rounding; tested against
    Phi^T W Phi)."""
    theta = jnp.pi * (x + half) / (2.0 * half)
    p = jnp.arange(2 * n_basis + 1, dtype=x.dtype)
    c1, c2 = jnp.cos(theta[:, 0, None] * p), jnp.cos(theta[:, 1, None] * p)
    c = c1.T @ (weight[:, None] * c2)
    j = np.arange(1, n_basis + 1)
    dif, tot = np.abs(j[:, None] - j[None, :]), j[:, None] + j[None, :]  # (j, k) per axis

    def at(i1, i2):  # (j1, k1, j2, k2) -> C[i1[j1, k1], i2[j2, k2]]
        return c[i1[:, :, None, None], i2[None, None, :, :]]

    g4 = at(dif, dif) - at(dif, tot) - at(tot, dif) + at(tot, tot)
    m = n_basis * n_basis
    return g4.transpose(0, 2, 1, 3).reshape(m, m) / (4.0 * half[0] * half[1])


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
    return woodbury_nlml(h, phi.T @ (weight * y), gram, omega2, y, weight, nu)


def woodbury_nlml(h: Hyper, phi_wy, gram, omega2, y, weight, nu: float) -> Float[Array, ""]:
    """`basis_nlml` from Phi^T W y (m,) instead of Phi (`project` gives it from the sine factors)."""
    sn2 = jnp.exp(h.log_noise)
    sl = jnp.sqrt(spectral_density(omega2, jnp.exp(h.log_length), jnp.exp(h.log_variance), nu))
    m = omega2.shape[0]
    # symmetric by construction; jnp.linalg.cholesky's symmetrisation cost 4x the factorisation on this CPU
    b = jnp.eye(m, dtype=y.dtype) + sl[:, None] * gram * sl[None, :] / sn2
    chol = jax.lax.linalg.cholesky(b, symmetrize_input=False)
    u = sl * phi_wy / sn2
    v = jax.scipy.linalg.solve_triangular(chol, u, lower=True)
    n = jnp.sum(weight > 0)
    quad = jnp.sum(weight * y * y) / sn2 - jnp.sum(v * v)
    logdet = n * jnp.log(sn2) - _sum_log_weight(weight) + 2.0 * jnp.sum(jnp.log(jnp.diag(chol)))
    return 0.5 * (quad + logdet + n * jnp.log(2.0 * jnp.pi))


def _sum_log_weight(weight):
    valid = weight > 0
    return jnp.sum(jnp.where(valid, jnp.log(jnp.where(valid, weight, 1.0)), 0.0))


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


class _Linear(eqx.Module):
    """The ranges' model linearised about (a_k, b_k): y = y0 - J delta, J = (d|p - a| / da, 1) per range
    (the height column zero on a flat path), as the m- and 4-sized products the likelihood needs:
    Phi^T W [y0, J] (m, 5), y0^T W y0, J^T W y0 (4,), J^T W J (4, 4)."""

    proj: Float[Array, "m 5"]
    yy: Float[Array, ""]
    jy: Float[Array, " 4"]
    jj: Float[Array, "4 4"]


def _linearise(factors, xc, r, m, weight, anchor, bias, free) -> _Linear:
    dist = _cone(xc, anchor)
    y0 = jnp.where(m, r - dist - bias, 0.0)
    unit = (anchor - xc) / jnp.where(dist > 0, dist, 1.0)[:, None]
    jac = jnp.where(m[:, None], jnp.concatenate([unit, jnp.ones_like(dist)[:, None]], axis=1), 0.0) * free
    wy, wj = weight * y0, weight[:, None] * jac
    proj = project(factors, jnp.concatenate([wy[:, None], wj], axis=1))
    return _Linear(proj, jnp.sum(wy * y0), jac.T @ wy, jac.T @ wj)


def _profile_length(
    log_l, lin: _Linear, gram, omega2, free, nv, sum_log_w, bounds, box, init, nu: float, max_steps: int
):
    """The negative log marginal likelihood of the linearised model at the length scale exp(log_l), minimised
    over (log s_f^2, log s_n^2) (BFGS, 2-D) and the step delta of (anchor, bias) (generalised least squares,
    in closed form): (value, (log s_f^2, log s_n^2), delta (4,), outcome code).

    One eigendecomposition D^1/2 G D^1/2 = U E U^T (D the unit-variance spectral density at l) makes every
    value O(m): with rho = s_f^2 / s_n^2, B = I + rho D^1/2 G D^1/2 has log|B| = sum log(1 + rho e_i) and
    u^T B^-1 u = sum c_i^2 / (1 + rho e_i) for c = U^T D^1/2 Phi^T W y (`woodbury_nlml`'s terms)."""
    sd = jnp.sqrt(spectral_density(omega2, jnp.exp(log_l), 1.0, nu))
    e, u = jnp.linalg.eigh(sd[:, None] * gram * sd[None, :])
    # directions the data do not see (e = 0 up to rounding) have c = 0: dropped, not amplified by rho
    seen = e > _EIG_FLOOR * jnp.max(e)
    e = jnp.where(seen, e, 0.0)
    q = jnp.where(seen[:, None], u.T @ (sd[:, None] * lin.proj), 0.0)
    c0, cj = q[:, 0], q[:, 1:]
    held = jnp.diag(1.0 - free)  # a held height: delta_z = 0
    lo, hi = box

    def value(h2):
        # the likelihood inside a box far wider than the soft bounds (a guard against BFGS's first steps),
        # the penalty on the raw values pulls back from outside it
        log_sf2, log_sn2 = jnp.clip(h2[0], lo, hi), jnp.clip(h2[1], lo, hi)
        rho, sn2 = jnp.exp(log_sf2 - log_sn2), jnp.exp(log_sn2)
        g = rho / (1.0 + rho * e)
        info = lin.jj - cj.T @ (g[:, None] * cj) + held
        rhs = lin.jy - cj.T @ (g * c0)
        delta = jnp.linalg.solve(info, rhs)
        quad = (lin.yy - c0 @ (g * c0) - rhs @ delta) / sn2
        logdet = nv * log_sn2 - sum_log_w + jnp.sum(jnp.log1p(rho * e))
        pen = hyper_penalty(Hyper(log_l, h2[0], h2[1]), *bounds) + 0.5 * jnp.sum((h2 - jnp.clip(h2, lo, hi)) ** 2)
        return 0.5 * (quad + logdet + nv * jnp.log(2.0 * jnp.pi)) + nv * pen, delta

    sol: optx.Solution = optx.minimise(
        lambda h2, _: value(h2)[0] / nv, optx.BFGS(rtol=1e-9, atol=1e-9), init, max_steps=max_steps, throw=False
    )
    val, delta = value(sol.value)
    return val, sol.value, delta, S.outcome(sol)


_GOLDEN = 0.5 * (math.sqrt(5.0) - 1.0)


def _search_length(profile, lo, hi, n_grid: int, n_golden: int):
    """argmin of the 1-D `profile` (log l -> value) over [lo, hi]: the best of `n_grid` points (n_grid > 1), or
    the middle of [lo, hi] (n_grid = 1), then a golden-section search in the bracket of one grid step either
    side of it. Returns the log length scale."""
    step = (hi - lo) / max(n_grid - 1, 1)
    if n_grid > 1:
        grid = lo + step * jnp.arange(n_grid, dtype=lo.dtype)
        best = grid[jnp.argmin(jax.lax.map(profile, grid))]
    else:
        best = 0.5 * (lo + hi)
        step = 0.5 * (hi - lo)
    a, b = best - step, best + step
    c, d = b - _GOLDEN * (b - a), a + _GOLDEN * (b - a)

    def shrink(carry, _):
        a, b, c, d, fc, fd = carry
        left = fc < fd  # the minimum is in [a, d]
        a, b = jnp.where(left, a, c), jnp.where(left, d, b)
        new = jnp.where(left, b - _GOLDEN * (b - a), a + _GOLDEN * (b - a))
        fn = profile(new)
        c, d = jnp.where(left, new, d), jnp.where(left, c, new)
        fc, fd = jnp.where(left, fn, fd), jnp.where(left, fc, fn)
        return (a, b, c, d, fc, fd), None

    (a, b, c, d, fc, fd), _ = jax.lax.scan(shrink, (a, b, c, d, profile(c), profile(d)), None, length=n_golden)
    return jnp.where(fc < fd, c, d)


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
    n_outer = max(2, max_steps // 20)

    def one(x, r, m, s, a0, b0, fz):
        nv = jnp.maximum(jnp.sum(m), 1)
        centre, half = domain(x[:, :2], m, margin)
        origin = jnp.concatenate([centre, (jnp.sum(jnp.where(m, x[:, 2], 0.0)) / nv)[None]])
        xc = jnp.where(m[:, None], x - origin, 0.0)
        weight = jnp.where(m, 1.0 / s, 0.0)
        factors = sine_factors(xc[:, :2], half, n_basis)
        gram = basis_gram(xc[:, :2], weight, half, n_basis)
        omega2 = jnp.sum((jnp.pi * idx / (2.0 * half)) ** 2, axis=-1)
        res = jnp.where(m, r - _cone(xc, a0 - origin) - b0, 0.0)
        var = jnp.maximum(jnp.sum(weight * res**2) / nv, 1e-6)
        radius = jnp.max(jnp.where(m, jnp.linalg.norm(xc[:, :2], axis=-1), 0.0))
        l_min = _RESOLUTION * jnp.max(half) / n_basis
        l_max = jnp.maximum(max_length * radius, 2.0 * l_min)
        bounds = (jnp.log(l_max), jnp.log(min_signal * var), jnp.log(l_min), jnp.log(max_signal * var))
        free = jnp.stack([1.0, 1.0, jnp.where(fz, 1.0, 0.0), 1.0]).astype(x.dtype)
        h_init = jnp.full(2, jnp.log(0.5 * var))
        lo, hi = jnp.log(l_min) - _SEARCH_MARGIN, jnp.log(l_max) + _SEARCH_MARGIN
        box = (jnp.log(min_signal * var) - _BOX, jnp.log(max_signal * var) + _BOX)
        fixed = (gram, omega2, free, nv, _sum_log_weight(weight), bounds, box, h_init, nu, max_steps)

        def relinearise(carry):
            anchor, bias, log_l, _, it, _ = carry
            lin = _linearise(factors, xc, r, m, weight, anchor, bias, free)

            def profile(ll):
                return _profile_length(ll, lin, *fixed)[0]

            # the first linearisation searches the whole range of l; later ones (steps of mm) near the last l
            log_l = jax.lax.cond(
                it == 0,
                lambda: _search_length(profile, lo, hi, _N_GRID, _N_GOLDEN),
                lambda: _search_length(profile, log_l - _LOCAL, log_l + _LOCAL, 1, _N_GOLDEN),
            )
            _, h2, delta, code = _profile_length(log_l, lin, *fixed)
            step = jnp.max(jnp.abs(delta))
            return anchor + delta[:3], bias + delta[3], log_l, h2, it + 1, (step, code)

        def more(carry):
            step, _ = carry[-1]
            return (carry[-2] < n_outer) & (step > _STEP_TOL)

        start = (a0 - origin, b0, 0.5 * (lo + hi), h_init, 0, (jnp.asarray(jnp.inf, x.dtype), S.CONVERGED))
        anchor, bias, log_l, h2, _, (step, code) = jax.lax.while_loop(more, relinearise, start)
        code = jnp.where(step > _STEP_TOL, S.MAX_STEPS, code)
        th = SpaceModel(anchor, bias, Hyper(log_l, h2[0], h2[1]))
        init = SpaceModel(a0 - origin, b0, Hyper(0.5 * (lo + hi), h_init[0], h_init[1]))
        z0 = a0[2] - origin[2]

        def nlml(th):
            anchor = th.anchor.at[2].set(jnp.where(fz, th.anchor[2], z0))
            y = jnp.where(m, r - _cone(xc, anchor) - th.bias, 0.0)
            phi_wy = project(factors, (weight * y)[:, None])[:, 0]
            # the penalty per range: the likelihood of 1e4-1e5 ranges would overrule a fixed one
            return woodbury_nlml(th.hyper, phi_wy, gram, omega2, y, weight, nu) + nv * hyper_penalty(th.hyper, *bounds)

        ok = jnp.isfinite(nlml(th))
        th = jax.tree.map(lambda a, b: jnp.where(ok, a, b), th, init)
        cov = laplace_covariance(nlml, th)
        # a held height has no curvature (the Hessian's floor made its variance ~1e4 m^2, which sent the mirror
        # check's profile far along the normal): zero here, the nls covariance floor gives it nls's variance
        held = free[:3, None] * free[None, :3]
        return th.anchor + origin, cov * held, th.bias, th.hyper, code

    # lax.map, not vmap: one anchor's factors in memory at a time, and batched eigendecompositions are slow on CPU
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
