"""Sparse Levenberg-Marquardt of the batch fit (mesh.sparse_lm) and single-node relocation (mesh.relocation)
against dense, obviously-correct references."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from jax.flatten_util import ravel_pytree

from jaxcal.mesh import batch as B
from jaxcal.mesh.relocation import neighbour_table, relocation_moves
from jaxcal.mesh.sparse_lm import normal_equations


def network(rng, n=9, span=20.0, noise=0.1):
    x = rng.uniform(0, span, (n, 2))
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    iu, ju = np.triu_indices(n, 1)
    keep = d[iu, ju] < 0.8 * span  # not every pair: a sparse graph
    i, j = iu[keep], ju[keep]
    z = d[i, j] + rng.normal(0, noise, i.size)
    z[0] += 3.0  # one gross outlier
    obs = B.Observations(jnp.asarray(i), jnp.asarray(j), jnp.asarray(z), jnp.ones(i.size))
    return x, obs


@pytest.mark.parametrize("loss", B.LOSSES)
@pytest.mark.parametrize("bias", ["network", "node"])
def test_rows_equal_the_dense_jacobian_of_the_residuals(rng, loss, bias):
    x, obs = network(rng)
    nb = B._Numbers.of(B.BatchParams(loss=loss, bias=bias))
    st = B._State(
        jnp.asarray(x + rng.normal(0, 0.3, x.shape)), jnp.asarray(-0.2), jnp.asarray(rng.normal(0, 0.05, x.shape[0]))
    )
    flat, unravel = ravel_pytree(st)

    def dense(v):
        return jnp.concatenate([jnp.atleast_1d(a) for a in B._residuals(unravel(v), (obs, nb))])

    f, g, idx = B._rows(st, (obs, nb))
    jac = np.zeros((f.shape[0], flat.shape[0]))
    np.add.at(jac, (np.arange(f.shape[0])[:, None].repeat(idx.shape[1], 1), np.asarray(idx)), np.asarray(g))
    np.testing.assert_allclose(f, dense(flat), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(jac, jax.jacfwd(dense)(flat), rtol=1e-10, atol=1e-12)
    h, grad = normal_equations(f, g, idx, flat.shape[0])
    h2, grad2 = normal_equations(f, g, idx, flat.shape[0], chunk=7)  # chunked accumulation, ragged end
    np.testing.assert_allclose(h, jac.T @ jac, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(grad, jac.T @ np.asarray(f), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(h2, h, rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(grad2, grad, rtol=1e-12, atol=1e-10)


@pytest.mark.parametrize("loss", ["l2", "cauchy", "mixture"])
def test_sparse_lm_reaches_the_optimum_of_optimistix_dense_lm(rng, loss):
    """Same starts, same problem: the sparse solver and optx.LevenbergMarquardt reach the same cost and
    the same positions up to a rigid motion (the fit's gauge)."""
    x, obs = network(rng)
    nb = B._Numbers.of(B.BatchParams(loss=loss))
    y0 = B._State(
        jnp.asarray(np.stack([x + rng.normal(0, 0.5, x.shape) for _ in range(3)])),
        jnp.zeros(3),
        jnp.zeros((3, x.shape[0])),
    )
    gnc = jnp.asarray([4.0, 2.0, 1.0])
    sp, c_sp, code_sp = B._fit_starts(y0, obs, nb, "lm", 1e-10, 300, gnc)
    de, c_de, _ = B._fit_starts(y0, obs, nb, "lm_dense", 1e-10, 300, gnc)
    np.testing.assert_allclose(c_sp, c_de, rtol=1e-8)
    from jaxcal import solver

    assert (np.asarray(code_sp) == solver.CONVERGED).all()  # what batch reports (`jaxcal.solver`)
    for k in range(3):
        assert float(B._procrustes_rmse(sp.x[k], de.x[k])) < 1e-6
        np.testing.assert_allclose(sp.c[k], de.c[k], atol=1e-6)


@pytest.mark.parametrize("bias", ["network", "none"])
def test_offsets_solved_apart_reach_the_full_solve(rng, bias):
    """Without per-node offsets in the model their block of J^T J is diagonal and uncoupled: solving it
    apart (`diag_tail`, the default path of `solve`) takes the same steps as the full Cholesky."""
    x, obs = network(rng, n=12)
    nb = B._Numbers.of(B.BatchParams(bias=bias))
    y0 = B._State(
        jnp.asarray(np.stack([x + rng.normal(0, 0.5, x.shape) for _ in range(3)])),
        jnp.zeros(3),
        jnp.asarray(rng.normal(0, 1e-3, (3, x.shape[0]))),
    )
    gnc = jnp.asarray([4.0, 2.0, 1.0])
    full, c_full, _ = B._fit_starts(y0, obs, nb, "lm", 1e-10, 300, gnc, 1e-4)
    apart, c_apart, code = B._fit_starts(y0, obs, nb, "lm", 1e-10, 300, gnc, 1e-4, x.shape[0])
    from jaxcal import solver

    assert (np.asarray(code) == solver.CONVERGED).all()
    np.testing.assert_allclose(c_apart, c_full, rtol=1e-9)
    np.testing.assert_allclose(apart.x, full.x, atol=1e-7)
    np.testing.assert_allclose(apart.b, full.b, atol=1e-12)


def test_sparse_lm_result_is_successful_and_exact_on_noise_free_data(rng):
    x, obs = network(rng, noise=0.0)
    obs = eqx.tree_at(lambda o: o.z, obs, obs.z.at[0].add(-3.0))  # no outlier: an exact fit exists
    nb = B._Numbers.of(B.BatchParams(loss="l2"))
    y0 = B._State(jnp.asarray(x + rng.normal(0, 0.3, x.shape)), jnp.asarray(0.0), jnp.zeros(x.shape[0]))
    sol = optx.least_squares(B._residuals, B._solver("lm", 1e-12), y0, (obs, nb), max_steps=200, throw=False)
    assert sol.result == optx.RESULTS.successful
    assert float(B._procrustes_rmse(sol.value.x, jnp.asarray(x))) < 1e-8


def test_relocation_moves_equal_a_dense_reference(rng):
    """Grid moves and the locally refined cost change equal a direct evaluation over all pairs: the best
    grid point outside the current basin, and the total cost of the network with that node moved and
    its coordinates minimised (others fixed) minus the current total cost."""
    from scipy.optimize import minimize

    x, obs = network(rng, n=8)
    p = B.BatchParams(loss="cauchy")
    nb = B._Numbers.of(p)
    m = x.shape[0]
    d_pair = np.full((m, m), np.nan)
    d_pair[np.asarray(obs.i), np.asarray(obs.j)] = d_pair[np.asarray(obs.j), np.asarray(obs.i)] = np.asarray(obs.z)
    nbr, dn, wn = neighbour_table(d_pair, np.isfinite(d_pair).astype(float))
    grid_n, exclude = 24, 1.0
    moved, delta = relocation_moves(
        jnp.asarray(x),
        jnp.zeros(nbr.shape),
        jnp.asarray(nbr),
        jnp.asarray(dn),
        jnp.asarray(wn),
        jax.tree_util.Partial(B._rho_of, nb),
        jax.tree_util.Partial(B._sqrt_rho_of, nb),
        grid_n,
        jnp.asarray(exclude),
        n_steps=60,
    )
    # the reference cost of the whole network, compiled once (the same shapes for every moved network)
    cost = jax.jit(lambda xx: B._cost(B._State(xx, jnp.asarray(0.0), jnp.zeros(m)), (obs, nb)))
    total = lambda xx: float(cost(jnp.asarray(xx)))  # noqa: E731
    lo, hi = x.min(0), x.max(0)
    mg = 0.25 * np.max(hi - lo)
    gx, gy = np.meshgrid(
        np.linspace(lo[0] - mg, hi[0] + mg, grid_n), np.linspace(lo[1] - mg, hi[1] + mg, grid_n), indexing="ij"
    )
    g = np.stack([gx.ravel(), gy.ravel()], 1)
    for k in range(m):

        def moved_cost(pt, k=k):
            xx = x.copy()
            xx[k] = pt
            return total(xx)

        xs = np.repeat(x[None], g.shape[0], axis=0)
        xs[:, k] = g
        costs = np.array(jax.vmap(cost)(jnp.asarray(xs)))  # every grid point's moved network at once
        costs[np.linalg.norm(g - x[k], axis=1) < exclude] = np.inf
        np.testing.assert_allclose(moved[k], g[np.argmin(costs)], atol=1e-9)
        best = minimize(
            moved_cost, np.asarray(moved[k]), method="Nelder-Mead", options=dict(xatol=1e-10, fatol=1e-12, maxiter=4000)
        ).fun
        np.testing.assert_allclose(float(delta[k]), best - total(x), atol=1e-6)


def test_large_network_leaves_nodes_outside_the_rigid_frame_unplaced():
    """Item 4 of issue #26 on a network (the sparse path, local relocation: N = 16 > relocate_candidates): a
    node that ranges a single neighbour and one that ranges two are not fixed by the ranges; both come out
    NaN, the rest placed."""
    from jaxcal.sim.mesh import simulate
    from jaxcal.sim.network import network_scenario

    n, weak = 16, (14, 15)
    ds = simulate(network_scenario(n, seed=3, n_epochs=5), seed=3)
    assert n > B.BatchParams().relocate_candidates  # relocation is local, not exhaustive
    r = np.array(ds.range)
    for node, keep in zip(weak, (1, 2), strict=True):
        nbrs = np.flatnonzero(np.isfinite(r[:, node]).any(axis=0))
        drop = [k for k in nbrs if k not in weak][keep:]
        r[:, node, drop] = r[:, drop, node] = np.nan
    ds = eqx.tree_at(lambda d: d.range, ds, r)
    res = B.calibrate(ds, {"estimate": "map", "summary": "median", "smacof_iters": 100}, config="conf1")
    assert np.isnan(res.position[list(weak)]).all()
    assert np.isfinite(res.position[np.setdiff1d(np.arange(n), weak)]).all()
