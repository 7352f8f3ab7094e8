"""The pair covariance's shared amplitude t_S (`jaxcal.mesh.pair_covariance`) per network: capture, then
recompute any rule for it offline at the same estimates.

`capture` runs the mesh methods on the family networks (`uncertainty_families.network`, or fresh noise
draws of one layout with `--draws`: the same nodes, walls and unmeasured pairs, new simulator noise and
pair offsets) or on the real recordings (`--real`, as `uncertainty_real.py`), and pickles per (network,
method): the result, the truth in its frame, b_hat, var(b_hat), b_info and the variance components, the
inputs of the pair covariance, and each node's final covariance with the shared amplitude matrix set to
0 and to each unit matrix. Every method's final covariance is affine in that matrix (pgp / parametric: the
pair covariance plus the displacement term; batch `estimate=mean`: the posterior excess plus the pair
covariance; batch `estimate=map`: the union with the all-ranges Laplace covariance, affine wherever the
pair covariance is the larger, which it is here by two orders of magnitude), so any rule for t_S is
recomputed exactly from these.

`compare` prints, per pickled (family, method) and rule, the coverage of the 95 % ellipses of the
well-connected nodes, NEES/dof per network (median, worst) and the nodes outside, as
`uncertainty_families.py` does. Rules (`--rules`, comma-separated): `main` (as run: b_hat^2 + var(b_hat),
the flat prior), `gauss:T` (Gaussian prior N(0, T) on b), `hcauchy:S` (half-Cauchy of scale S spreads,
b >= 0), `hflat` (flat on b >= 0), `hc` (flat, var(b_hat) from the residuals (HC0) instead of the fitted
components), `tI:V` / `tN:V` (batch and pgp: V m^2 added to t_I / t_N, t_S as run), `texp[:HOW[:ONLY]]` (batch
and pgp: t_I, t_D, t_N raised to their values given the moment estimate and its sampling covariance,
`expected_components`; t_S as run; `texpfull:...` sets them, lowering too).

Usage (B = benchmarks/uncertainty_shared_amplitude.py):
    python B capture --family weak --seeds 1,3 --methods "batch;pgp" --out DIR
    python B capture --family weak --seeds 9 --draws 0-7 --methods batch:estimate=map --out DIR
    python B capture --real campus_sport,torgau --methods "batch:estimate=map;pgp" --out DIR
    python B compare --rules main,gauss:9,hcauchy:1 "DIR/weak-*.pkl"
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import pickle
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import chi2, norm

sys.path.insert(0, str(Path(__file__).resolve().parent))

FORCE: list = [None]  # the shared amplitude matrix to use instead of the rule (None: the rule)
LAST: dict = {}  # what the last pair covariance estimated
CALL: dict = {}  # per calibrate call: the captured covariances


def _basis(q: int) -> list[np.ndarray]:
    """0 and the symmetric unit matrices E_ab (a <= b) of size q."""
    out = [np.zeros((q, q))]
    for a in range(q):
        for b in range(a, q):
            e = np.zeros((q, q))
            e[a, b] = e[b, a] = 1.0
            out.append(e)
    return out


def _install() -> None:
    """Wrap the pair covariance's amplitude rule and its callers in pgp and batch (capture only)."""
    import jaxcal.mesh.pair_covariance as pc
    from jaxcal.mesh.batch import driver as bd

    amp_rule, parts, comps = pc._shared_amplitude, pc._parts, pc._components

    def amp_hook(b_hat, cov_b, info):
        LAST["amp"] = {"b_hat": np.array(b_hat), "cov_b": np.array(cov_b), "info": np.array(info)}
        return amp_rule(b_hat, cov_b, info) if FORCE[0] is None else np.array(FORCE[0], dtype=float)

    def parts_hook(t, amp, b_hat, info):
        LAST["t"] = np.array(t)
        return parts(t, amp, b_hat, info)

    def comps_hook(*args):
        if FORCE[0] is None:
            LAST["inputs"] = [x if x is None or isinstance(x, int) else np.array(x) for x in args]
        return comps(*args)

    def each_basis(fn, *a, **k):
        FORCE[0] = None
        LAST.clear()
        main = fn(*a, **k)
        amp = dict(LAST.get("amp", {}), inputs=LAST.get("inputs"))
        t, outs = LAST.get("t"), []
        if "b_hat" in amp and np.all(np.isfinite(amp["b_hat"])):
            for e in _basis(len(amp["b_hat"])):
                FORCE[0] = e
                outs.append(fn(*a, **k))
            FORCE[0] = None
        return main, {"main": main, "basis": outs, "amp": amp, "t": t}

    poscov, plc, union, per_node = pc.position_covariance, bd._pair_level_covariance, bd.covariance_union, bd._per_node

    def poscov_hook(*a, **k):
        main, CALL["pgp"] = each_basis(poscov, *a, **k)
        return main

    def plc_hook(*a, **k):
        main, CALL["pending"] = each_basis(plc, *a, **k)
        return main

    def union_hook(a, b):
        out = union(a, b)
        pend = CALL.get("pending")
        if pend is not None and "union" not in pend:
            f = a.shape[0]
            p0 = pend["main"][:f, :f]
            pend["union"] = [union(a, b - p0 + pb[:f, :f]) for pb in pend["basis"]]
            pend["union_main"] = out
        return out

    def per_node_hook(prob, mask, cov_f, defined):
        out = per_node(prob, mask, cov_f, defined)
        pend = CALL.get("pending")
        if pend is not None and pend.get("union_main") is cov_f:
            CALL["batch"] = dict(pend, main=out, basis=[per_node(prob, mask, u, defined) for u in pend["union"]])
            CALL.pop("pending")
        return out

    pc._shared_amplitude, pc._parts, pc._components = amp_hook, parts_hook, comps_hook
    pc.position_covariance, bd._pair_level_covariance = poscov_hook, plc_hook
    bd.covariance_union, bd._per_node = union_hook, per_node_hook


def network_draw(seed: int, draw: int, **family):
    """`uncertainty_families.network(seed)`'s layout, walls and unmeasured pairs with fresh noise and offsets."""
    import uncertainty_families as uf

    import jaxcal.sim.mesh as sm
    from jaxcal.data import MeshDataset

    simulate = sm.simulate
    sm.simulate = lambda sc, seed=0: simulate(sc, seed=100_000 + 100 * seed + draw)
    try:
        ds = uf.network(seed, pair_offset_m=0.0, **family)
    finally:
        sm.simulate = simulate
    n = len(ds.node_ids)
    iu, ju = np.triu_indices(n, 1)
    off = np.zeros((n, n))
    off[iu, ju] = np.random.default_rng(200_000 + 100 * seed + draw).normal(0.0, 0.04, iu.size)
    r = (ds.range.astype(np.float64) + (off + off.T)[None]).astype(np.float32)
    return MeshDataset(
        name=ds.name, node_ids=ds.node_ids, time=ds.time, range=r, truth=ds.truth, los=ds.los, configs=ds.configs
    )


def _record(res, truth, well, name, key, method, draw, seconds) -> dict:
    kind = "pgp" if method.split(":")[0] in ("pgp", "parametric") else "batch"
    cap = CALL.get(kind)
    return {
        "family": name,
        "seed": key,
        "draw": draw,
        "method": method,
        "position": np.asarray(res.position),
        "covariance": None if res.covariance is None else np.asarray(res.covariance),
        "truth": np.asarray(truth),
        "well": well,
        "a0": res.frame_anchors()[0],
        "cap": None if cap is None else {k: cap[k] for k in ("main", "basis", "amp", "t")},
        "seconds": seconds,
    }


def _jobs(args):
    """(name, key, draw, dataset, well) per network."""
    import uncertainty_families as uf

    if args.real:
        import tempfile

        import uncertainty_real as ur

        with tempfile.TemporaryDirectory() as tmp:
            for name, ds in ur.datasets(Path(tmp), args.real.split(",")):
                for cname, _ in ds.configs:
                    yield name, cname, None, ds, np.ones(len(ds.node_ids), bool)
        return
    fam = uf.FAMILIES[args.family]
    for seed in uf.parse_seeds(args.seeds):
        for draw in uf.parse_seeds(args.draws) if args.draws else [None]:
            ds = uf.network(seed, **fam) if draw is None else network_draw(seed, draw, **fam)
            yield args.family, seed, draw, ds, uf.rigid_nodes(ds)


def capture(args) -> None:
    import logging

    import jax

    jax.config.update("jax_enable_x64", True)
    logging.getLogger("jaxcal").setLevel(logging.ERROR)
    import uncertainty_families as uf

    from jaxcal.methods import calibrate
    from jaxcal.metrics import truth_in_result_frame

    _install()
    os.makedirs(args.out, exist_ok=True)
    for name, key, draw, ds, well in _jobs(args):
        for m in args.methods.split(";"):
            tag = f"{name}-{key}-{m.replace(':', '_')}" + ("" if draw is None else f"-d{draw}")
            fn = os.path.join(args.out, tag + ".pkl")
            if os.path.exists(fn):
                continue
            CALL.clear()
            t0 = time.perf_counter()
            if args.real:
                meth, _, sets = m.partition(":")
                res = calibrate(ds, meth, dict(kv.split("=", 1) for kv in sets.split(",") if kv), key)
            else:
                res = uf.run(m, ds)
            truth = truth_in_result_frame(res, np.asarray(ds.truth, dtype=float)[:, :2])
            rec = _record(res, truth, well, name, key, m, draw, time.perf_counter() - t0)
            with open(fn, "wb") as f:
                pickle.dump(rec, f)
            amp = (rec["cap"] or {}).get("amp", {})
            print(
                json.dumps(
                    {
                        "run": tag,
                        "s": round(rec["seconds"], 1),
                        **{k: np.asarray(amp[k]).tolist() for k in ("b_hat", "cov_b", "info") if k in amp},
                    }
                ),
                flush=True,
            )


# ---- offline: node covariances under another rule, and the family figures


def cov_at(rec: dict, amp: np.ndarray | None) -> np.ndarray:
    """(N, 2, 2) final covariances with the shared amplitude matrix `amp` (None: as run)."""
    r, cap = rec["covariance"], rec["cap"]
    if r is None:
        return np.full((len(rec["position"]), 2, 2), np.nan)
    if amp is None or cap is None or not cap["basis"]:
        return r
    b0 = cap["basis"][0]
    cur = b0 + sum(amp[a, b] * (bk - b0) for (a, b), bk in zip(_pairs(amp.shape[0]), cap["basis"][1:], strict=True))
    out = r.copy()
    ok = np.isfinite(r).all(axis=(1, 2)) & np.isfinite(cur - cap["main"]).all(axis=(1, 2))
    out[ok] = r[ok] + (cur - cap["main"])[ok]
    return out


def _pairs(q: int) -> list[tuple[int, int]]:
    return [(a, b) for a in range(q) for b in range(a, q)]


def expected_bb(b_hat, cov_b, log_prior=None, n: int = 4001) -> np.ndarray:
    """E[b b^T] under the likelihood N(b_hat, cov_b) and a prior on b_0 alone (`log_prior`, flat if None; the
    other amplitudes flat): quadrature over b_0, the others Gaussian given it."""
    b, c = np.asarray(b_hat, float), np.asarray(cov_b, float)
    if log_prior is None or c[0, 0] <= 0:
        return np.outer(b, b) + c
    sd = np.sqrt(c[0, 0])
    g = np.linspace(b[0] - 12 * sd, b[0] + 12 * sd, n)
    lw = -0.5 * ((g - b[0]) / sd) ** 2 + log_prior(g)
    w = np.exp(lw - lw.max())
    w /= w.sum()
    out = np.zeros((b.size, b.size))
    out[0, 0] = w @ (g * g)
    if b.size > 1:
        k = c[1:, 0] / c[0, 0]
        cm = b[1:][None, :] + np.outer(g - b[0], k)
        out[0, 1:] = out[1:, 0] = w @ (g[:, None] * cm)
        out[1:, 1:] = (cm * w[:, None]).T @ cm + c[1:, 1:] - np.outer(c[1:, 0], c[0, 1:]) / c[0, 0]
    return out


def _hc(rec) -> tuple[np.ndarray, np.ndarray]:
    """b_hat and its heteroskedasticity-consistent (HC0, dof-corrected) covariance from the pair residuals."""
    jac, e, w, spread, _i, _j, _n, prior, shared = rec["cap"]["amp"]["inputs"]
    m = len(e)
    pat = np.asarray(spread, float)[:, None] if shared is None else np.asarray(shared, float).reshape(m, -1)
    g = np.linalg.solve((jac.T * w) @ jac + np.diag(prior), jac.T * w)
    pp = pat - jac @ (g @ pat)
    a = pp * (w / w.max())[:, None]
    gi = np.linalg.inv(a.T @ pp)
    b = gi @ (a.T @ e)
    r = e - pp @ b
    dof = max(m - np.linalg.matrix_rank(jac) - pat.shape[1], 1)
    return b, gi @ ((a * (r * r)[:, None]).T @ a) @ gi.T * m / dof


def _batch_components(rec, d_t: np.ndarray) -> np.ndarray:
    """(N, 2, 2) final covariances with d_t (3,) m^2 added to (t_I, t_D, t_N), t_S as run (batch: the union with
    the Laplace covariance taken as the pair covariance, as in `cov_at`; pgp: the pair covariance's block of the
    free coordinates, exact). d_t may be negative where the sum stays non-negative."""
    jac, e, w, spread, i, j, n_nodes, prior, _shared = rec["cap"]["amp"]["inputs"]
    s, m = np.asarray(spread, float), len(e)
    g = np.linalg.solve((jac.T * w) @ jac + np.diag(prior), jac.T * w)
    z = np.zeros((m, n_nodes))
    z[np.arange(m), i] = z[np.arange(m), j] = 1.0
    gz = g @ z
    d = d_t[0] * g @ g.T + d_t[1] * (g * s * s) @ g.T + d_t[2] * gz @ gz.T
    out = rec["covariance"].copy()
    idx = []  # free coordinates in order: a1 x only, then both coordinates of each node with a covariance
    for k in range(len(out)):
        if k != rec["a0"] and np.isfinite(out[k]).all():
            idx += [(k, 0)] if out[k][1, 1] <= 1e-12 else [(k, 0), (k, 1)]
    for p, (k, ax) in enumerate(idx):
        for q, (k2, ax2) in enumerate(idx):
            if k2 == k:
                out[k, ax, ax2] += d[p, q]
    return out


def component_posterior(rec) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t as fitted (3 + Q,), mu, C, h): the weighted moment estimate of (t_I, t_D, t_N, t_S per pattern) without the
    sign constraint (mu) and its covariance C under Gaussian residuals of the fitted covariance R
    (Cov(r_k r_l, r_m r_n) = R_km R_ln + R_kn R_lm); h (3 + Q,) sum_k wn_k^2 X_a,kk, each component's share of
    the weighted residual sum of squares. Dense (M^2 / 2 moment equations squared): small networks only."""
    jac, e, w, spread, i, j, n_nodes, prior, shared = rec["cap"]["amp"]["inputs"]
    m, s = len(e), np.asarray(spread, float)
    pat = s[:, None] if shared is None else np.asarray(shared, float).reshape(m, -1)
    proj = np.eye(m) - jac @ np.linalg.solve((jac.T * w) @ jac + np.diag(prior), jac.T * w)
    z = np.zeros((m, n_nodes))
    z[np.arange(m), i] = z[np.arange(m), j] = 1.0
    comps = [np.eye(m), np.diag(s * s), z @ z.T] + [np.outer(c, c) for c in pat.T]
    xs = [proj @ v @ proj.T for v in comps]
    wn = w / w.max()
    ku, lu = np.triu_indices(m)
    om = wn[ku] * wn[lu]
    design = np.column_stack([x[ku, lu] for x in xs]) * om[:, None]
    mu = np.linalg.lstsq(design, np.outer(e, e)[ku, lu] * om, rcond=None)[0]
    t = np.asarray(rec["cap"]["t"], float)
    r = sum(tk * x for tk, x in zip(t, xs, strict=True))
    cov_y = (r[np.ix_(ku, ku)] * r[np.ix_(lu, lu)] + r[np.ix_(ku, lu)] * r[np.ix_(lu, ku)]) * np.outer(om, om)
    h = np.linalg.pinv(design.T @ design) @ design.T
    return t, mu, h @ cov_y @ h.T, np.array([wn**2 @ np.diag(x) for x in xs])


def _truncated(mu, sd, median: bool = False):
    """Mean (or median) of N(mu, sd^2) truncated to >= 0, closed form (mu + sd phi(a) / Phi(a), a = mu / sd)."""
    mu, sd = np.asarray(mu, float), np.asarray(sd, float)
    a = mu / np.maximum(sd, 1e-300)
    val = mu + sd * (norm.isf(np.exp(norm.logcdf(a)) / 2) if median else np.exp(norm.logpdf(a) - norm.logcdf(a)))
    return np.where(sd > 0, np.maximum(val, 0.0), np.maximum(mu, 0.0))


def _draws(mean, cov, n_draws):
    lam, vec = np.linalg.eigh(cov)
    x = mean + np.random.default_rng(0).standard_normal((n_draws, len(mean))) @ (vec * np.sqrt(np.maximum(lam, 0))).T
    return x[(x >= 0).all(axis=1)]


def expected_components(rec, how: str = "joint", only: str = "IDN", n_draws: int = 200_000) -> np.ndarray:
    """(3 + Q,) the components given the data under `component_posterior` restricted to t >= 0 (flat prior).

    how: `joint` E[t | t >= 0] of all jointly (Monte Carlo; tsamp's `texp`); `marg` each component's
    own truncated mean (closed form); `margz` the same for the zeroed components only; `cond` / `condmed` each
    zeroed component's truncated mean / median given the others at their fitted values (closed form);
    `setmed` the zeroed components' joint truncated median given the nonzero ones (Monte Carlo); a suffix `rs`
    (`margrs`, `condrs`) rescales t_I, t_D, t_N so that the weighted residual variance they explain,
    sum_a t_a sum_k wn_k^2 X_a,kk, is the fit's (the data pin the total; the split is what is uncertain).
    `total`: E[t | t >= 0] jointly at the fit's (t_I, t_D, t_N) share of that total (Monte Carlo).
    `only`: which of t_I, t_D, t_N may change (e.g. "N")."""
    if how.endswith("rs"):
        t, _, _, h = component_posterior(rec)
        ex, h = expected_components(rec, how[:-2], only, n_draws), h[:3]
        return np.r_[ex[:3] * (h @ t[:3] / (h @ ex[:3]) if h @ ex[:3] > 0 else 1.0), ex[3:]]
    t, mu, c, h = component_posterior(rec)
    sd = np.sqrt(np.maximum(np.diag(c), 0.0))
    zero = t <= 0
    if how == "total":  # the fit's total where it has one (else nothing to split: as fitted)
        h3 = np.r_[h[:3], 0.0 * h[3:]]
        hc = c @ h3
        if not (h3 @ hc > 0 and h3 @ t > 0):
            return t
        mu, c = mu + hc * (h3 @ (t - mu)) / (h3 @ hc), c - np.outer(hc, hc) / (h3 @ hc)
    if how in ("joint", "total"):
        x = _draws(mu, c, n_draws)
        ex = x.mean(axis=0) if len(x) > 100 else (t if how == "total" else np.maximum(mu, 0.0))
    elif how in ("marg", "margz"):
        ex = _truncated(mu, sd)
        ex = np.where(zero | (how == "marg"), ex, t)
    elif how in ("cond", "condmed"):
        p, ex = np.linalg.pinv(c), t.copy()
        for k in np.flatnonzero(zero & (p.diagonal() > 0)):
            o = np.arange(t.size) != k
            mc = mu[k] - p[k, o] @ (t[o] - mu[o]) / p[k, k]
            ex[k] = _truncated(mc, 1.0 / np.sqrt(p[k, k]), how == "condmed")
    elif how == "setmed":
        zk, nk, ex = np.flatnonzero(zero), np.flatnonzero(~zero), t.copy()
        if zk.size:
            p = np.linalg.pinv(c)
            cz = np.linalg.pinv(p[np.ix_(zk, zk)])
            x = _draws(mu[zk] - cz @ p[np.ix_(zk, nk)] @ (t[nk] - mu[nk]), cz, n_draws)
            if len(x) > 100:
                ex[zk] = np.median(x, axis=0)
    else:
        raise ValueError(f"unknown rule texp:{how}")
    keep = np.array(["IDN"[k] not in only for k in range(3)] + [True] * (t.size - 3))
    return np.where(keep, t, ex)


def rule_cov(rec: dict, rule: str) -> np.ndarray:
    """(N, 2, 2) final covariances of a pickled record under `rule` (see the module docstring)."""
    name, _, arg = rule.partition(":")
    cap = rec["cap"]
    if name == "main" or cap is None or not cap["basis"]:
        return cov_at(rec, None)
    amp = cap["amp"]
    if name in ("texp", "texpfull"):  # texp[:HOW[:ONLY]] raises t_I, t_D, t_N to the rule's values, texpfull sets them
        how, _, only = (arg or "joint").partition(":")
        d_t = expected_components(rec, how, only or "IDN")[:3] - cap["t"][:3]
        return _batch_components(rec, d_t if name.endswith("full") else np.maximum(d_t, 0.0))
    if name in ("tI", "tN"):
        d_t = np.zeros(3)
        d_t[0 if name == "tI" else 2] = float(arg)
        return _batch_components(rec, d_t)
    if name == "hc":
        b, c = _hc(rec)
        return cov_at(rec, np.outer(b, b) + c)
    priors = {
        "gauss": lambda x: -0.5 * x * x / float(arg),
        "hcauchy": lambda x: np.where(x >= 0, -np.log1p((x / float(arg)) ** 2), -np.inf),
        "hflat": lambda x: np.where(x >= 0, 0.0, -np.inf),
    }
    return cov_at(rec, expected_bb(amp["b_hat"], amp["cov_b"], priors[name]))


def network_figures(rec: dict, cov: np.ndarray) -> dict | None:
    """NEES/dof, per-node inside flags, RMS error and predicted RMS over the well-connected nodes (a0 excluded)."""
    rows = []
    for k, (e, c) in enumerate(zip(rec["position"] - rec["truth"], cov, strict=True)):
        if k == rec["a0"] or not rec["well"][k] or not (np.isfinite(e).all() and np.isfinite(c).all()):
            continue
        free = np.diag(c) > 1e-12
        cf = c[np.ix_(free, free)]
        q = float(e[free] @ np.linalg.solve(cf, e[free])) if np.all(np.linalg.eigvalsh(cf) > 0) else np.inf
        rows.append((int(free.sum()), q, q <= chi2.ppf(0.95, int(free.sum())), float(e @ e), float(np.trace(c))))
    if not rows:
        return None
    return {
        "nees": sum(r[1] for r in rows) / sum(r[0] for r in rows),
        "inside": [r[2] for r in rows],
        "rmse": float(np.sqrt(np.mean([r[3] for r in rows]))),
        "pred": float(np.sqrt(np.mean([r[4] for r in rows]))),
    }


def compare(args) -> None:
    recs = []
    for pattern in args.files:
        for fn in sorted(glob.glob(pattern)):
            with open(fn, "rb") as f:
                recs.append(pickle.load(f))

    def key(r):  # noise draws of a layout apart from the family networks
        return (r["family"] + ("" if r.get("draw") is None else " draws"), r["method"])

    for fam, meth in sorted({key(r) for r in recs}):
        group = [r for r in recs if key(r) == (fam, meth)]
        for rule in args.rules.split(","):
            if rule.partition(":")[0] in ("tI", "tN", "texp", "texpfull") and meth.startswith("parametric"):
                continue  # batch's and pgp's free-coordinate layouts only
            figs = [(r["seed"], r.get("draw"), network_figures(r, rule_cov(r, rule))) for r in group]
            figs = [x for x in figs if x[2] is not None]
            if not figs:
                continue
            inside = np.concatenate([f["inside"] for *_, f in figs])
            nees = np.array([f["nees"] for *_, f in figs])
            line = {
                "family": fam,
                "method": meth,
                "rule": rule,
                "networks": len(figs),
                "nodes": int(inside.size),
                "coverage95": round(float(inside.mean()), 3),
                "nees_dof_median": round(float(np.median(nees)), 2),
                "nees_dof_worst": round(float(nees.max()), 2),
                "outside": int((~inside).sum()),
                "per_network": {
                    f"{s}" + ("" if d is None else f"/d{d}"): [
                        round(f["nees"], 2),
                        round(f["rmse"], 2),
                        round(f["pred"], 2),
                    ]
                    for s, d, f in figs
                },
            }
            print(json.dumps(line), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    cap = sub.add_parser("capture")
    cap.add_argument("--family", default="weak")
    cap.add_argument("--seeds", default="1")
    cap.add_argument("--draws", default="", help="fresh noise draws of each seed's layout, e.g. 0-7")
    cap.add_argument("--real", default="", help="real recordings instead of the family, e.g. campus_sport,torgau")
    cap.add_argument("--methods", default="batch;batch:estimate=map;pgp")
    cap.add_argument("--out", required=True)
    cmp_ = sub.add_parser("compare")
    cmp_.add_argument("--rules", default="main,gauss:9,hcauchy:1,hflat")
    cmp_.add_argument("files", nargs="+", help="pickles (glob patterns) written by capture")
    args = ap.parse_args(argv)
    (capture if args.cmd == "capture" else compare)(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
