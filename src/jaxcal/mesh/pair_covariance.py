"""Covariance of a mesh fit under per-pair systematic errors whose size is estimated from the data.

Repeated ranges of one pair share its systematic error (antenna delays, static multipath, an NLOS excess
delay), so averaging epochs does not shrink it: the pair, not the range, is the unit. A pair's
systematic error u_k moves the fit by A^-1 J_k^T w_k u_k (A = J^T W J, w_k the weight the estimator
gives pair k: the sum of its ranges' IRLS weights at the estimate), so

    Cov = A^-1 J^T W Sigma W J A^-1,    Sigma = Cov(u),

and the question is Sigma. It is a variance-component model whose components are estimated from the pair
residuals r = z - model (z the per-pair median, which does not depend on the fit), with the projection
M = I - J A^-1 J^T W that the fit applies to them (r = M u to first order: the part of an error that
the geometry absorbs is *not* in the residuals, and E[r r^T] = M Sigma M^T accounts for it):

    Sigma = t_I I + t_D diag(s^2) + t_N Z Z^T + t_S s s^T

- t_I: an independent error per pair (antenna-delay mismatch, static multipath);
- t_D: independent, larger for pairs whose own ranges scatter more (s_k: 1.4826 MAD of the pair's ranges
  over epochs and both directions; NLOS pairs scatter more);
- t_N: a per-node error shared by every pair of the node (Z: pairs x nodes incidence; antenna delays);
- t_S: an error of one sign shared by the pairs that scatter (an NLOS excess delay is positive on every
  NLOS pair: its contributions add up instead of averaging out).

t_I, t_D, t_N (and a first t_S) come from a non-negative least-squares fit of the upper triangle of
r r^T on that of M V_c M^T (method of moments), each entry (k, l) weighted by w_k w_l / max(w)^2: a pair
the robust fit ignores (a gross-outlier pair, metres off) neither moves the estimate nor sizes the errors
of the others (unweighted, two such pairs of the simulated torgau hall made t_I = 1.2 m^2 and every
node's predicted error 1-4 m for 0.1-0.3 m errors). The shared component is the one the geometry can hide
completely (a node whose pairs all scatter moves with their common excess, and its residuals stay
small), so its amplitude b (u = b s + ...) is estimated by (the same weighted) least squares on what the pattern
leaves in the residuals, a = M s: b_hat = a^T r / a^T a, with variance a^T V a / (a^T a)^2 under the other components
(V = M Sigma_0 M^T), and t_S is the expected b^2 under that estimate, b_hat^2 + var(b_hat): where the
residuals cannot size the excess (a small: the geometry absorbs it) the covariance says so instead of
assuming it is zero. (Generalised least squares with V^+ was tried first: where the fitted components
leave V singular, e.g. t_I = 0 on a real mesh with centimetre-quantised spreads, 1 / (a^T V^+ a) blew up
to covariances of tens of metres.) No parameter is set by hand.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls
from scipy.sparse import csr_matrix


def pair_spread(range_m: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """(M,) robust scatter [m] of each pair's ranges: 1.4826 MAD over epochs and both directions (0 where
    a pair has fewer than two ranges)."""
    r = np.asarray(range_m, dtype=np.float64)
    pooled = np.concatenate([r[:, i, j], r[:, j, i]], axis=0)
    cnt = np.isfinite(pooled).sum(axis=0)
    out = np.zeros(len(i))
    ok = cnt > 1
    if ok.any():
        med = np.nanmedian(pooled[:, ok], axis=0)
        out[ok] = 1.4826 * np.nanmedian(np.abs(pooled[:, ok] - med), axis=0)
    return out


def _parts(t, amp, b_hat, info) -> dict:
    """The fitted variance components as plain numbers (the `parts` of the result's params)."""
    return {
        "t_I": float(t[0]),
        "t_D": float(t[1]),
        "t_N": float(t[2]),
        "t_S": np.diag(amp).tolist(),
        "b_hat": np.atleast_1d(b_hat).tolist(),
        "b_info": np.atleast_1d(info).tolist(),
    }


def _shared_amplitude(b_hat: np.ndarray, cov_b: np.ndarray, info: np.ndarray) -> np.ndarray:
    """(Q, Q) expected b b^T of the shared amplitudes given their least-squares estimate `b_hat` (Q,) and its
    covariance `cov_b` (Q, Q) under the other components (flat prior); `info` (Q,) a^T a per pattern."""
    return np.outer(b_hat, b_hat) + cov_b


def variance_components(
    jac: np.ndarray,
    e: np.ndarray,
    w: np.ndarray,
    spread: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    n_nodes: int,
    prior_prec: np.ndarray,
    shared: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """Sigma (M, M) of the pair errors and its components (see the module docstring).

    Args:
        jac: (M, P) Jacobian of the pair errors (or of the model: only J^T W J and J appear) with respect
            to the P parameters; e: (M,) pair errors z - model at the estimate [m]; w: (M,) weights of the
            pairs in the estimator (> 0); spread: (M,) `pair_spread`; i, j: (M,) node indices of the pairs;
            n_nodes: number of nodes; prior_prec: (P,) prior precisions of the parameters (0 for none);
            shared: (M, Q) patterns of errors shared by all pairs with one amplitude each (default: the
            spread alone, `s`; an estimator without a range offset adds a column of ones).

    Returns:
        (Sigma, {"t_I", "t_D", "t_N", "t_S" (Q amplitudes^2 expected), "b_hat", "b_info"}).
    """
    m = len(e)
    a_inv = np.linalg.inv((jac.T * w) @ jac + np.diag(prior_prec))
    proj = np.eye(m) - jac @ a_inv @ (jac.T * w)
    z = np.zeros((m, n_nodes))
    z[np.arange(m), i] = 1.0
    z[np.arange(m), j] = 1.0
    s = np.asarray(spread, dtype=np.float64)
    pat = s[:, None] if shared is None else np.asarray(shared, dtype=np.float64).reshape(m, -1)
    comps = [np.eye(m), np.diag(s * s), z @ z.T] + [np.outer(c, c) for c in pat.T]
    # moment equations weighted as the estimator weighs the pairs (w / max w, product over the two pairs
    # of an entry): a pair the robust fit ignores (a gross-outlier pair, metres off) neither moves the
    # estimate nor sizes the errors of the others
    wn = w / np.max(w)
    tu = np.triu_indices(m)
    om = (wn[:, None] * wn[None, :])[tu]
    design = np.column_stack([(proj @ v @ proj.T)[tu] for v in comps]) * om[:, None]
    t = nnls(design, np.outer(e, e)[tu] * om)[0]
    sigma0 = t[0] * comps[0] + t[1] * comps[1] + t[2] * comps[2]
    a = proj @ pat  # (M, Q): what each shared pattern leaves in the residuals
    a = a * wn[:, None]  # weighted least squares, the same weights
    gram = a.T @ (proj @ pat)
    lam = np.linalg.eigvalsh(gram) if np.isfinite(gram).all() else np.zeros(1)
    if lam.min() > 1e-12 * max(lam.max(), 1e-300):
        ginv = np.linalg.inv(gram)
        b_hat = ginv @ (a.T @ e)  # least squares; its covariance under the other components (sandwich)
        cov_b = ginv @ a.T @ (proj @ sigma0 @ proj.T) @ a @ ginv.T
        info = np.diag(gram)
        amp = _shared_amplitude(b_hat, cov_b, info)
    else:  # a pattern that leaves nothing in the residuals (e.g. constant, with a fitted offset)
        b_hat, amp, info = np.full(pat.shape[1], np.nan), np.diag(t[3:]), np.diag(gram)
    sigma = sigma0 + pat @ amp @ pat.T
    return sigma, _parts(t, amp, b_hat, info)


def _incidence(i: np.ndarray, j: np.ndarray, m: int, n_nodes: int) -> csr_matrix:
    """(M, n_nodes) sparse pair-node incidence Z (Z[k, i_k] = Z[k, j_k] = 1)."""
    rows = np.r_[np.arange(m), np.arange(m)]
    return csr_matrix((np.ones(2 * m), (rows, np.r_[i, j])), shape=(m, n_nodes))


def _components(jac, e, w, spread, i, j, n_nodes, prior_prec, shared):
    """`variance_components` without an M x M matrix product: the same estimates at O(M^2 P) time and O(M^2)
    memory instead of O(M^3) and a design of M^2 / 2 rows (thousands of pairs in a network of hundreds of
    nodes). Returns (t (3 + Q,), amp (Q, Q), pat (M, Q), B (P, M), parts): Sigma = t_I I + t_D diag(s^2) + t_N Z Z^T +
    pat amp pat^T, never formed.

    The weighted moment equations are solved through their Gram matrix: with X_a = M V_a M^T (M the
    projection), D = diag(wn^2) and the upper triangle's entries weighted wn_k wn_l, the design's Gram
    entries are (tr(V_a Q V_b Q) + sum_k wn_k^4 X_a,kk X_b,kk) / 2 with Q = M^T D M = D - E B - (E B)^T +
    B^T (J^T D J) B (B = A^-1 J^T W, E = D J), each trace a sum over the (weighted) squares of Q, Q Z or
    Q s; the right-hand side is (r^T V_a r + sum_k wn_k^4 e_k^2 X_a,kk) / 2 with r = M^T D e.
    """
    m = len(e)
    s = np.asarray(spread, dtype=np.float64)
    pat = s[:, None] if shared is None else np.asarray(shared, dtype=np.float64).reshape(m, -1)
    a_inv = np.linalg.inv((jac.T * w) @ jac + np.diag(prior_prec))
    b = a_inv @ (jac.T * w)  # (P, M): proj = I - J B
    wn = w / np.max(w)
    d = wn * wn
    z = _incidence(i, j, m, n_nodes)
    # Q = proj^T D proj, the one M x M matrix (built in place)
    q = (jac * d[:, None]) @ b
    q += q.T
    q = (b.T @ ((jac.T * d) @ jac)) @ b - q
    q[np.diag_indices(m)] += d
    q2 = q * q
    qz = np.asarray((z.T @ q).T)  # Q Z (M, N)
    qp = q @ pat  # Q pat (M, Qp)
    del q
    diag_v = [np.ones(m), s * s]
    n_c = 3 + pat.shape[1]
    tr = np.zeros((n_c, n_c))
    q2v = [q2 @ v for v in diag_v]
    del q2
    for a in range(2):
        for c in range(2):
            tr[a, c] = diag_v[a] @ q2v[c]
        tr[a, 2] = diag_v[a] @ np.sum(qz * qz, axis=1)
        tr[a, 3:] = diag_v[a] @ (qp * qp)
    tr[2, 2] = np.sum(np.asarray(z.T @ qz) ** 2)
    tr[2, 3:] = np.sum(np.asarray(z.T @ qp) ** 2, axis=0)
    tr[3:, 3:] = (pat.T @ qp) ** 2
    tr = np.triu(tr) + np.triu(tr, 1).T
    # diagonals of X_a = proj V_a proj^T (proj = I - J B)
    jb_diag = np.einsum("kp,pk->k", jac, b)
    xd = np.zeros((m, n_c))
    for a, v in enumerate(diag_v):
        xd[:, a] = v * (1.0 - 2.0 * jb_diag) + np.sum((jac @ ((b * v) @ b.T)) * jac, axis=1)
    pz = np.asarray(z.todense()) - jac @ np.asarray((z.T @ b.T).T)  # proj Z (M, N)
    xd[:, 2] = np.sum(pz * pz, axis=1)
    pp = pat - jac @ (b @ pat)  # proj pat
    xd[:, 3:] = pp * pp
    d2 = d * d
    gram_d = 0.5 * (tr + (xd * d2[:, None]).T @ xd)
    r = d * e - b.T @ (jac.T @ (d * e))  # proj^T D e
    rv = np.r_[r @ r, (s * s) @ (r * r), np.sum(np.asarray(z.T @ r) ** 2), (pat.T @ r) ** 2]
    h = 0.5 * (rv + xd.T @ (d2 * e * e))
    # non-negative least squares on the Gram form: ||R t - R^-T h|| with G = R^T R
    lam_g, vec_g = np.linalg.eigh(gram_d)
    good = lam_g > 1e-14 * max(lam_g.max(), 1e-300)
    rmat = (vec_g[:, good] * np.sqrt(lam_g[good])).T
    t = nnls(rmat, (vec_g[:, good].T @ h) / np.sqrt(lam_g[good]))[0]

    def sigma0_dot(u):  # Sigma_0 u without forming Sigma_0 (M, k)
        return t[0] * u + t[1] * (s * s)[:, None] * u + t[2] * np.asarray(z @ (z.T @ u))

    a_pat = pp * wn[:, None]
    gram = a_pat.T @ pp
    lam = np.linalg.eigvalsh(gram) if np.isfinite(gram).all() else np.zeros(1)
    if lam.min() > 1e-12 * max(lam.max(), 1e-300):
        ginv = np.linalg.inv(gram)
        b_hat = ginv @ (a_pat.T @ e)
        u = a_pat - b.T @ (jac.T @ a_pat)  # proj^T a
        cov_b = ginv @ (u.T @ sigma0_dot(u)) @ ginv.T
        info = np.diag(gram)
        amp = _shared_amplitude(b_hat, cov_b, info)
    else:
        b_hat, amp, info = np.full(pat.shape[1], np.nan), np.diag(t[3:]), np.diag(gram)
    return t, amp, pat, b, _parts(t, amp, b_hat, info)


def pair_covariance(
    jac: np.ndarray,
    e: np.ndarray,
    w: np.ndarray,
    spread: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    n_nodes: int,
    prior_prec: np.ndarray,
    shared: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """(P, P) covariance A^-1 J^T W Sigma W J A^-1 of the parameters under the pair-error model
    (`variance_components`; arguments as there). Symmetric positive semi-definite; NaN rows and columns
    for parameters the pairs do not fix (those in the null space of A = J^T W J + prior)."""
    jac = np.asarray(jac, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)
    prior_prec = np.asarray(prior_prec, dtype=np.float64)
    p = jac.shape[1]
    out = np.full((p, p), np.nan)
    try:
        lam, vec = np.linalg.eigh((jac.T * w) @ jac + np.diag(prior_prec))
        null = lam <= 1e-10 * max(float(lam.max()), 1e-300)
        keep = (vec[:, null] ** 2).sum(axis=1) < 1e-6
        if not keep.any():
            return out, {}
        jk, pk = jac[:, keep], prior_prec[keep]
        e = np.asarray(e, dtype=np.float64)
        t, amp, pat, g, parts = _components(jk, e, w, spread, np.asarray(i), np.asarray(j), n_nodes, pk, shared)
    except (np.linalg.LinAlgError, ValueError):
        return out, {}
    # g = A^-1 J^T W (P', M): each pair's influence on the parameters; Cov = g Sigma g^T term by term (each
    # PSD: t >= 0, amp PSD), never forming the (M, M) Sigma
    s2 = np.asarray(spread, dtype=np.float64) ** 2
    gz = np.asarray((_incidence(np.asarray(i), np.asarray(j), len(e), n_nodes).T @ g.T).T)
    gp = g @ pat
    cov = t[0] * (g @ g.T) + t[1] * ((g * s2) @ g.T) + t[2] * (gz @ gz.T) + gp @ amp @ gp.T
    out[np.ix_(keep, keep)] = 0.5 * (cov + cov.T)
    return out, parts


def position_covariance(
    range_m: np.ndarray,
    position: np.ndarray,
    anchors: tuple[int, int, int],
    offset: bool = False,
    robust_scale: float | None = None,
    displacement: str = "node",
) -> np.ndarray:
    """(N, D, D) covariance of a mesh estimate `position` (frame `anchors`) under per-pair systematic
    errors. Without a fitted range offset (`offset=False`) a common offset of all ranges is one more
    shared pattern (a column of ones) whose amplitude the residuals estimate: the estimator carries its
    effect. NaN for nodes without a finite position or that the pairs do not fix; zeros on the
    coordinates the frame fixes.

    With `robust_scale` None: the covariance of an estimator that weighs every measured pair alike
    (least-squares influence), at `position` itself. With a scale s [m] (e.g. a grid filter's sigma_r,
    whose estimate is not a least-squares fit): the pairs' medians are first fitted by Cauchy-robust least
    squares of scale s over the free coordinates (`robust_fit`: from `position` and from the pairs' MDS
    layout, whichever ends lower), the covariance is that
    of this fit (pairs weighted by their Cauchy weights 1 / (1 + (e / s)^2) at it, so a pair metres off
    neither moves it nor sizes the others' errors), and each node's displacement d from the fit to
    `position` is added (`displacement`: "node", d d^T; "network", its variance shared by the network's nodes,
    gross nodes with their own d d^T as well: `_displacement_term`)."""
    x = np.asarray(position, dtype=np.float64)
    n, d = x.shape
    a0, a1, a2 = anchors
    placed = np.asarray(np.isfinite(x).all(axis=1))
    out = np.full((n, d, d), np.nan)
    r = np.asarray(range_m, dtype=np.float64)
    from jaxcal.mesh.batch import observations  # noqa: PLC0415 - batch imports this module

    i, j, zmed, _ = observations(r, "median")
    ok = placed[i] & placed[j]
    i, j, zmed = i[ok], j[ok], zmed[ok]
    if i.size == 0 or not placed[[a0, a1, a2]].all():
        return out
    mask = np.zeros((n, d), dtype=bool)
    mask[placed] = True
    mask[a0] = False
    mask[a1, 1:] = False
    if d == 3:
        mask[a2, 2] = False
    free = np.flatnonzero(mask.ravel())
    x_fit, w = x, np.ones(i.size)
    if robust_scale is not None:
        x_fit = robust_fit(x, i, j, zmed, free, float(robust_scale), anchors)
    diff = x_fit[i] - x_fit[j]
    dist = np.linalg.norm(diff, axis=1)
    u = diff / np.maximum(dist, 1e-12)[:, None]
    full = np.zeros((i.size, n * d))
    rows = np.arange(i.size)
    for k in range(d):
        full[rows, i * d + k] = u[:, k]
        full[rows, j * d + k] = -u[:, k]
    jac = full[:, free]
    e = zmed - dist
    if robust_scale is not None:
        w = 1.0 / (1.0 + (e / float(robust_scale)) ** 2)
    spread = pair_spread(r, i, j)
    if offset:
        jac = np.column_stack([jac, np.ones(i.size)])
        shared = spread[:, None]
    else:
        shared = np.column_stack([spread, np.ones(i.size)])
    if i.size - jac.shape[1] < 3 + shared.shape[1]:
        # fewer redundant pairs than variance components: the residuals cannot size the pairs' errors (with
        # only the frame nodes placed, 3 pairs for 3 coordinates, the shared amplitudes came out at 10^4-10^5 m
        # in one direction and nothing in the other)
        return out
    cov, _ = pair_covariance(jac, e, w, spread, i, j, n, np.zeros(jac.shape[1]), shared)
    cov_all = np.zeros((n * d, n * d))
    cov_all[np.ix_(free, free)] = cov[: free.size, : free.size]
    for node in np.flatnonzero(placed):
        out[node] = cov_all[node * d : (node + 1) * d, node * d : (node + 1) * d]
    dev = np.where(mask, x - x_fit, 0.0)
    out = out + _displacement_term(dev, mask, displacement)
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def _displacement_term(dev: np.ndarray, mask: np.ndarray, how: str) -> np.ndarray:
    """(N, D, D) the covariance term of the estimate's displacement `dev` (N, D) from the robust fit (zero on the
    coordinates the frame fixes, `mask` False).

    `node`: each node's own d d^T. `network`: the displacement is an error of the estimator (a grid's cells, a
    filter's lag) whose size the network's nodes share: sigma^2 = the mean square of the free coordinates'
    displacements, on every free coordinate, except for *gross* nodes, whose displacement lies beyond the
    99.9 % quantile of chi-square under the robust scale (1.4826 MAD of the coordinates): they keep their own
    d d^T as well and are left out of sigma^2. (`node` alone puts each node's realised error into its own
    ellipse: the truth is then inside by construction, coverage 100 %, NEES/dof 0.5-0.7 on the families.)"""
    node = dev[:, :, None] * dev[:, None, :]
    if how == "node":
        return node
    if how != "network":
        raise ValueError(f"unknown displacement term {how!r}")
    from scipy.stats import chi2  # noqa: PLC0415

    from jaxcal.mesh.batch import covariance_union  # noqa: PLC0415

    dof = mask.sum(axis=1)
    ok = np.isfinite(dev).all(axis=1) & (dof > 0)
    d_free = np.where(mask & ok[:, None], dev, 0.0)
    coords = np.abs(dev[mask & ok[:, None]])
    scale2 = (1.4826 * np.median(coords)) ** 2 if coords.size else 0.0
    ratio = np.sum(d_free**2, axis=1) / max(scale2, 1e-300)
    gross = ok & (ratio > chi2.ppf(0.999, np.maximum(dof, 1)))
    inlier = mask & (ok & ~gross)[:, None]
    var = float(np.mean(dev[inlier] ** 2)) if inlier.any() else 0.0
    out = np.zeros_like(node)
    k, a = np.nonzero(mask)
    out[k, a, a] = var
    for q in np.flatnonzero(gross):
        out[q] = covariance_union(out[q], node[q])
    return out


def robust_fit(
    x: np.ndarray, i: np.ndarray, j: np.ndarray, z: np.ndarray, free: np.ndarray, scale: float, anchors
) -> np.ndarray:
    """The Cauchy-robust fit of the pair ranges z that an estimate `x` (N, D) is measured against: `polish`
    from `x` and from the classical MDS layout of the pair ranges (shortest paths for the missing pairs,
    moved into the frame of `anchors`), whichever ends at the lower robust cost. From `x` alone, an estimate
    that is metres off in a wrong basin (a filter that diverged, a node on its mirror side) would be
    polished into that basin's local minimum, and its displacement from "the fit" would say it is right."""

    def cost(y):
        e = np.linalg.norm(y[i] - y[j], axis=1) - z
        return float(np.sum(np.log1p((e / scale) ** 2)))

    def fit(start):  # polished, and in the frame's half plane (a2 at y >= 0: the mirror fits the ranges alike)
        y = polish(start, i, j, z, free, scale)
        if y.shape[1] == 2 and y[anchors[2], 1] < 0:
            y = y * np.array([1.0, -1.0])
        return y

    best = fit(x)
    start = mds_start(x, i, j, z, anchors)
    if start is None:
        return best
    other = fit(start)
    return other if cost(other) < cost(best) - 1e-9 * max(1.0, cost(best)) else best


def mds_start(x: np.ndarray, i: np.ndarray, j: np.ndarray, z: np.ndarray, anchors) -> np.ndarray | None:
    """The classical MDS layout of the pair ranges z (pairs i, j; shortest paths for the missing pairs) of
    the placed rows of `x` (N, D), moved into the frame of `anchors`; NaN rows where `x` has them. None when
    the placed nodes' graph is not connected or the frame nodes coincide in it."""
    from scipy.sparse.csgraph import shortest_path  # noqa: PLC0415

    from jaxcal.mesh.frame import to_frame  # noqa: PLC0415

    n, d = x.shape
    placed = np.isfinite(x).all(axis=1)
    g = np.zeros((n, n))
    g[i, j] = g[j, i] = np.maximum(z, 1e-9)
    sub = np.flatnonzero(placed)
    dist = shortest_path(g[np.ix_(sub, sub)], method="D", directed=False)
    if not np.isfinite(dist).all():
        return None
    c = np.eye(sub.size) - 1.0 / sub.size
    lam, vec = np.linalg.eigh(-0.5 * c @ (dist * dist) @ c)
    start = np.full_like(x, np.nan)
    start[sub] = vec[:, ::-1][:, :d] * np.sqrt(np.maximum(lam[::-1][:d], 0.0))
    try:
        start = to_frame(start, *anchors)
    except (ValueError, ArithmeticError):
        return None
    return start if np.isfinite(start[sub]).all() else None


def polish(x: np.ndarray, i: np.ndarray, j: np.ndarray, z: np.ndarray, free: np.ndarray, scale: float) -> np.ndarray:
    """`x` (N, D) with its `free` coordinates (flat indices) fitted to the pair ranges z (pairs i, j)
    by Cauchy-robust least squares of scale `scale` [m] (scipy `least_squares`, trust region), from
    `x`; the other coordinates are kept. Returns `x` unchanged where the fit fails."""
    from scipy.optimize import least_squares  # noqa: PLC0415

    n, d = x.shape
    col = np.full(n * d, -1)
    col[free] = np.arange(free.size)
    rows = np.arange(i.size)

    def full(theta):
        y = x.ravel().copy()
        y[free] = theta
        return y.reshape(x.shape)

    def res(theta):
        y = full(theta)
        return np.linalg.norm(y[i] - y[j], axis=1) - z

    def jac(theta):  # d|y_i - y_j| / dy_i = u = -d/dy_j (analytic: a finite-difference one costs 2 N evaluations)
        y = full(theta)
        u = y[i] - y[j]
        u = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
        out = np.zeros((i.size, free.size))
        for a in range(d):
            for node, sign in ((i, 1.0), (j, -1.0)):
                c = col[node * d + a]
                ok = c >= 0
                np.add.at(out, (rows[ok], c[ok]), sign * u[ok, a])
        return out

    try:
        sol = least_squares(res, x.ravel()[free], jac=jac, loss="cauchy", f_scale=scale, method="trf", max_nfev=200)
    except (ValueError, np.linalg.LinAlgError):
        return x
    if not np.isfinite(sol.x).all():
        return x
    y = x.ravel().copy()
    y[free] = sol.x
    return y.reshape(x.shape)
