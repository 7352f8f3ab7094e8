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
r r^T on that of M V_c M^T (method of moments). The shared component is the one the geometry can hide
completely (a node whose pairs all scatter moves with their common excess, and its residuals stay
small), so its amplitude b (u = b s + ...) is estimated by generalised least squares, b_hat with
variance 1 / I_b (I_b = a^T V^+ a, a = M s, V = M Sigma_0 M^T the other components), and t_S is the
expected b^2 under that estimate, b_hat^2 + 1 / I_b: where the residuals cannot size the excess
(I_b small) the covariance says so instead of assuming it is zero. No parameter is set by hand.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls


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


def variance_components(jac: np.ndarray, e: np.ndarray, w: np.ndarray, spread: np.ndarray, i: np.ndarray,
                        j: np.ndarray, n_nodes: int, prior_prec: np.ndarray) -> tuple[np.ndarray, dict]:
    """Sigma (M, M) of the pair errors and its components (see the module docstring).

    Args:
        jac: (M, P) Jacobian of the pair errors (or of the model: only J^T W J and J appear) with respect
            to the P parameters; e: (M,) pair errors z - model at the estimate [m]; w: (M,) weights of the
            pairs in the estimator (> 0); spread: (M,) `pair_spread`; i, j: (M,) node indices of the pairs;
            n_nodes: number of nodes; prior_prec: (P,) prior precisions of the parameters (0 for none).

    Returns:
        (Sigma, {"t_I", "t_D", "t_N", "t_S", "b_hat", "b_info"}).
    """
    m = len(e)
    a_inv = np.linalg.inv((jac.T * w) @ jac + np.diag(prior_prec))
    proj = np.eye(m) - jac @ a_inv @ (jac.T * w)
    z = np.zeros((m, n_nodes))
    z[np.arange(m), i] = 1.0
    z[np.arange(m), j] = 1.0
    s = np.asarray(spread, dtype=np.float64)
    comps = [np.eye(m), np.diag(s * s), z @ z.T, np.outer(s, s)]
    tu = np.triu_indices(m)
    design = np.column_stack([(proj @ v @ proj.T)[tu] for v in comps])
    t = nnls(design, np.outer(e, e)[tu])[0]
    sigma0 = t[0] * comps[0] + t[1] * comps[1] + t[2] * comps[2]
    a = proj @ s
    v_plus = np.linalg.pinv(proj @ sigma0 @ proj.T, rcond=1e-10, hermitian=True)
    info = float(a @ v_plus @ a)
    if info > 0 and np.isfinite(info):
        b_hat = float(a @ v_plus @ e) / info
        t_s = b_hat**2 + 1.0 / info
    else:  # no shared pattern (every pair scatters alike, or no pair left over)
        b_hat, t_s = float("nan"), float(t[3])
    sigma = sigma0 + t_s * comps[3]
    return sigma, {"t_I": float(t[0]), "t_D": float(t[1]), "t_N": float(t[2]), "t_S": float(t_s),
                   "b_hat": b_hat, "b_info": info}


def pair_covariance(jac: np.ndarray, e: np.ndarray, w: np.ndarray, spread: np.ndarray, i: np.ndarray,
                    j: np.ndarray, n_nodes: int, prior_prec: np.ndarray) -> tuple[np.ndarray, dict]:
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
        sigma, parts = variance_components(jk, np.asarray(e, dtype=np.float64), w, spread, i, j, n_nodes, pk)
        a_inv = np.linalg.inv((jk.T * w) @ jk + np.diag(pk))
    except (np.linalg.LinAlgError, ValueError):
        return out, {}
    g = a_inv @ (jk.T * w)  # (P', M) influence of each pair's error on the parameters
    lam, vec = np.linalg.eigh(0.5 * (sigma + sigma.T))
    root = g @ (vec * np.sqrt(np.maximum(lam, 0.0)))  # Cov = root root^T: PSD by construction
    out[np.ix_(keep, keep)] = 0.5 * (root @ root.T + (root @ root.T).T)
    return out, parts
