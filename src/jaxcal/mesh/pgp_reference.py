"""Slow, plain NumPy reference of the PGP filter (paper 000, eq. 5-13), for tests only.

Written to be obviously correct rather than fast: linear probabilities, Python loops over nodes,
cells
and hypotheses, a1 as a genuine 1-D histogram over `[0, d_max]` (eq. 5), a2 on the cells with y >= 0
(eq. 6), every other node on the whole grid. It follows the conventions documented in `pgp`
(localisation rule, neighbour sets, update orders, hypothesis truncation, eq. 9 for "parametric").
Nodes are in filter order: index 0 is a0, 1 is a1, 2 is a2.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["run_reference", "run_reference_for"]


def _gauss(x: float, s: float) -> float:
    return math.exp(-0.5 * (x / s) ** 2)


def _kernel(e: float, s: float, nlos_weight: float, nlos_mean_m: float) -> float:
    """Range kernel of eq. (11) at range error e = z - distance: the Gaussian, or with
    `nlos_weight > 0` the LOS/NLOS mixture `(1 - w) gauss + w s sqrt(2 pi) EMG(e)`, where the EMG
    density (Gaussian(0, s) convolved with an exponential of mean `nlos_mean_m`) is written out."""
    if nlos_weight == 0.0:
        return _gauss(e, s)
    lam = 1.0 / nlos_mean_m
    phi = 0.5 * math.erfc(-(e / s - lam * s) / math.sqrt(2.0))
    emg = lam * math.exp(0.5 * (lam * s) ** 2 - lam * e) * phi
    return (1.0 - nlos_weight) * _gauss(e, s) + nlos_weight * s * math.sqrt(2 * math.pi) * emg


def run_reference(
    z: np.ndarray,
    dt: np.ndarray,
    n_half: int,
    cell_m: float,
    *,
    top_k: int,
    n_hyp: int,
    tau: float,
    r_est: float,
    sigma_r: float,
    v: float,
    sigma_v: float,
    p_out: float = 0.0,
    nlos_weight: float = 0.0,
    nlos_mean_m: float = 1.0,
    update_order: str = "jacobi",
    mode: str = "pgp",
    min_refs: int = 3,
    a2_all: bool = False,
) -> dict:
    """Run the filter with loops.

    Args:
        z: (K, N, N) symmetric ranges [m], NaN missing, nodes in filter order.
        dt: (K,) time steps [s]. n_half, cell_m: the grid (cells `(i - n_half) * cell_m`).
        Other arguments: as in `pgp.PGPParams`.

    Returns:
        dict with `posterior` (N, n, n) final probabilities on the common grid (a1 on its row, a0
        on the
        origin cell), `raw` (K, N, 2) eq. (13) estimates (NaN when not localised), `mass` (K, N)
        sums.
    """
    k_epochs, n = z.shape[0], z.shape[1]
    side = 2 * n_half + 1
    axis = [(i - n_half) * cell_m for i in range(side)]
    # regions: list of (flat index, x, y) per node; flat index ix * side + iy orders ties like
    # lax.top_k
    regions = []
    for i in range(n):
        cells = []
        for ix in range(side):
            for iy in range(side):
                x, y = axis[ix], axis[iy]
                if i == 0 and not (ix == n_half and iy == n_half):
                    continue
                if i == 1 and not (iy == n_half and ix >= n_half):  # the 1-D histogram bins h = 0..d_max
                    continue
                if i == 2 and iy < n_half:
                    continue
                cells.append((ix * side + iy, x, y))
        regions.append(cells)
    prob = [np.full(len(regions[i]), 1.0 / len(regions[i])) for i in range(n)]
    heard = np.zeros((n, n), dtype=bool)
    need = [0, 1, 2] + [min_refs] * (n - 3)

    def localised(i):
        return heard[i].sum() >= need[i]

    def allowed(i, j):
        if i == j or i == 0:
            return False
        if i == 1:
            return j == 0
        if i == 2 and not a2_all:
            return j in (0, 1)
        return True

    def ranked(i):
        # cells of node i by decreasing probability, ties by flat index
        return sorted(range(len(regions[i])), key=lambda m: (-prob[i][m], regions[i][m][0]))

    def estimate(i):
        m_best = ranked(i)[0]
        _, bx, by = regions[i][m_best]
        num_x = num_y = den = 0.0
        for m, (_, x, y) in enumerate(regions[i]):
            d2 = (x - bx) ** 2 + (y - by) ** 2
            if d2 < r_est * r_est or d2 == 0:
                num_x += prob[i][m] * x
                num_y += prob[i][m] * y
                den += prob[i][m]
        return num_x / den, num_y / den

    def covariance_trace(i):
        p = prob[i] / prob[i].sum()
        mx = sum(p[m] * x for m, (_, x, _) in enumerate(regions[i]))
        my = sum(p[m] * y for m, (_, _, y) in enumerate(regions[i]))
        return sum(p[m] * ((x - mx) ** 2 + (y - my) ** 2) for m, (_, x, y) in enumerate(regions[i]))

    def hypotheses(j):
        """[(x, y, weight)], sigma: eq. (10) (or eq. 9's point estimate for parametric)."""
        if mode == "parametric":
            x, y = estimate(j)
            return [(x, y, 1.0)], sigma_r + math.sqrt(max(covariance_trace(j), 0.0))
        taken, before = [], 0.0
        for m in ranked(j)[:n_hyp]:
            if before < tau or not taken:
                if prob[j][m] > 0 or not taken:
                    taken.append(m)
            before += prob[j][m]
        total = sum(prob[j][m] for m in taken)
        return [(regions[j][m][1], regions[j][m][2], prob[j][m] / total) for m in taken], sigma_r

    def update(i, zk, step_m, hyps, loc_now):
        cells = regions[i]
        # motion update, eq. (7)-(8), only once localised
        if loc_now[i]:
            src = ranked(i)[:top_k]
            prior = np.zeros(len(cells))
            for g, (_, x, y) in enumerate(cells):
                for m in src:
                    _, sx, sy = cells[m]
                    d = math.hypot(x - sx, y - sy)
                    prior[g] += prob[i][m] * _gauss(d - step_m, sigma_v)
        else:
            prior = prob[i].copy()
        # likelihood, eq. (11)
        lik = np.ones(len(cells))
        used = []
        for j in range(n):
            if not allowed(i, j) or not np.isfinite(zk[i, j]) or not loc_now[j]:
                continue
            used.append(j)
            hs, s = hyps[j]
            for g, (_, x, y) in enumerate(cells):
                acc = 0.0
                for hx, hy, w in hs:
                    e = zk[i, j] - math.hypot(x - hx, y - hy)
                    acc += w * _kernel(e, s, nlos_weight, nlos_mean_m)
                lik[g] *= (1.0 - p_out) * acc + p_out
        post = prior * lik  # eq. (12)
        return post / post.sum(), used

    raw = np.full((k_epochs, n, 2), np.nan)
    mass = np.zeros((k_epochs, n))
    for k in range(k_epochs):
        step_m = v * dt[k]
        if update_order == "jacobi":
            loc_now = [localised(i) for i in range(n)]
            hyps = {j: hypotheses(j) for j in range(n) if loc_now[j]}
            new = {}
            for i in range(1, n):
                new[i] = update(i, z[k], step_m, hyps, loc_now)
            for i, (p, used) in new.items():
                prob[i] = p
                heard[i, used] = True
        else:
            for i in range(1, n):
                loc_now = [localised(j) for j in range(n)]
                hyps = {j: hypotheses(j) for j in range(n) if loc_now[j]}
                p, used = update(i, z[k], step_m, hyps, loc_now)
                prob[i] = p
                heard[i, used] = True
        for i in range(n):
            mass[k, i] = prob[i].sum()
            if localised(i):
                raw[k, i] = estimate(i)
    post = np.zeros((n, side, side))
    for i in range(n):
        for m, (flat, _, _) in enumerate(regions[i]):
            post[i, flat // side, flat % side] = prob[i][m]
    return {"posterior": post, "raw": raw, "mass": mass}


def run_reference_for(params, cfg, inp, mode: str = "pgp", **override) -> dict:
    """`run_reference` with the settings of a `pgp.PGPParams` and the arrays of `pgp.prepare`.

    Args:
        params: a `PGPParams` (read by attribute). cfg, inp: `FilterConfig`, `FilterInputs` of
            `pgp.prepare` (grid, top_k, hypothesis cap, ranges, time steps). mode: "pgp" or
            "parametric". override: `run_reference` keywords to replace.
    """
    mix = params.range_model == "mixture"
    kw = dict(
        top_k=cfg.top_k,
        n_hyp=cfg.n_hyp,
        tau=params.tau,
        r_est=params.r_est,
        sigma_r=params.sigma_r,
        v=params.v,
        sigma_v=params.sigma_v,
        p_out=params.p_out,
        nlos_weight=params.nlos_weight if mix else 0.0,
        nlos_mean_m=params.nlos_mean_m,
        update_order=params.update_order,
        mode=mode,
        min_refs=params.min_refs,
        a2_all=params.a2_all,
    )
    kw.update(override)
    z, dt = np.asarray(inp.z, dtype=np.float64), np.asarray(inp.dt, dtype=np.float64)
    return run_reference(z, dt, cfg.grid.n_half, cfg.grid.cell_m, **kw)
