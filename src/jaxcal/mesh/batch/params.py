"""Parameters of `--method batch` (`BatchParams`, with their validation), the observation containers and what
`solve` returns (`BatchSolution`), and the host-side preprocessing of a range stream into observations."""

from __future__ import annotations

import equinox as eqx
import numpy as np
from jaxtyping import Array, Float, Int

from jaxcal.errors import JaxcalError

LOSSES = ("l2", "huber", "cauchy", "mixture")


BIASES = ("auto", "none", "network", "node")


SUMMARIES = ("median", "all")


INITS = ("multi", "cmds", "smacof")


SOLVERS = ("lm", "gn", "lm_dense")


PAIR_WEIGHTS = ("none", "spread")


ESTIMATES = ("map", "mean")
SAMPLERS = ("hmc", "nuts")


RHAT_MAX = 1.1  # split R-hat above which (or undefined) estimate=mean falls back to the fit (Gelman-Rubin)


class BatchParams(eqx.Module):
    """Parameters of `--method batch` (all settable with `--set KEY=VALUE`).

    Attributes:
        dim: 2 (planar) or 3 (positions in 3-D; a2 fixes the x-y plane).
        loss: robust loss: `l2`, `huber`, `cauchy` (default; redescending, ignores gross outliers),
            `mixture` (LOS Gaussian + exponentially modified Gaussian NLOS + uniform outliers).
        sigma_r: ranging standard deviation / loss scale [m] (LOS width of the mixture).
        bias: range offset model: `none`, `network` (one common offset, default), `node` (common offset
            plus one offset per node), `auto` (`network` or `none`, whichever a residual bootstrap of the
            network fit predicts to give the smaller position error; see `offset_bootstrap`).
        node_bias_sigma_m: prior standard deviation of the per-node offsets [m] (`bias=node`).
        summary: `all` (every range of every epoch, default; fitted by IRLS) or `median` (one robust
            range per pair).
        nlos_weight, nlos_mean_m: mixture share and mean excess length of NLOS ranges.
        outlier_weight, outlier_span_m: mixture share and span [m] of the uniform outlier floor.
        init: `multi` (classical MDS, SMACOF and random SMACOF starts; default), `cmds`, `smacof`.
        n_starts: number of random SMACOF starts (with `init=multi`), whatever N.
        smacof_iters: Guttman transforms per SMACOF run.
        solver: `lm` (Levenberg-Marquardt on the sparse normal equations of the pairs, default; see
            `jaxcal.mesh.sparse_lm`), `gn` (Gauss-Newton) or `lm_dense` (Optimistix's Levenberg-Marquardt
            on the dense Jacobian: the same optimum, at O(M P^2) per step).
        max_steps: iteration limit of the least-squares solver.
        tol: relative and absolute tolerance of the least-squares solver.
        seed: random seed of the random starts (and of the offset bootstrap).
        n_boot: bootstrap replicates of `bias=auto`.
        pair_weight: `none` (every pair counts alike) or `spread` (pairs whose ranges scatter more, over
            epochs and between the two directions, count less; see `spread_weights`).
        gnc_stages: graduated non-convexity: the multi-start fit runs with loss scales
            sigma_r * 2^(G-1), ..., sigma_r (G stages; 1 = no graduation).
        gnc_tol: tolerance of the stages before the last one (`solver=lm`; at most `tol` is never
            tightened): they only carry a start into the basin of the narrow loss, so converging them to
            `tol` spends steps that the last stage repeats (about half of the fit's steps at N = 100).
        relocate_rounds: rounds of single-node relocation after the multi-start fit: every node in
            turn is moved to the best point of a grid over the scene (its own robust cost, the
            others fixed), which undoes flips (mirror images of weakly constrained nodes) and
            placements pulled by a gross outlier; each move is refined and kept if the total cost drops.
            Every move is first refined locally (the node alone, its neighbours fixed: the exact change
            of the total cost, `jaxcal.mesh.relocation`); the `relocate_candidates` moves that lower the
            cost most are refined globally (all of them when N <= relocate_candidates: exhaustive).
        relocate_candidates: moves refitted globally per relocation round (see `relocate_rounds`).
        relocate_grid: grid points per axis of the relocation search (2-D; a third of it per axis in 3-D).
        irls_iters: reweighting rounds of the all-epochs refinement (`summary=all`).
        z_up: 3-D only: of the two mirror images (z -> -z), report the one where the nodes other than
            a0, a1, a2 lie mostly above the a0-a1-a2 plane (true) or below it (false).
        estimate: `mean` (default: posterior mean and sample covariance of the pair-level model, see
            `posterior_mean`; the minimum-mean-square-error estimate, which differs from the fit where
            the geometry is weak) or `map` (the robust fit itself and its Laplace covariance).
        student_nu: degrees of freedom of the Student-t pair likelihood of `estimate=mean` (1 = Cauchy).
        mcmc_chains, mcmc_steps: Hamiltonian Monte Carlo chains and transitions per chain of
            `estimate=mean` (a quarter of it, at most 500, is burn-in; `mcmc_steps` is the most run, see `mcmc_mcse`).
        mcmc_mcse: the sampler stops before `mcmc_steps` once the Monte Carlo error of the posterior mean is
            below this share of the posterior standard deviation in every coordinate and split R-hat is
            below 1.01 (checked every 250 transitions after the burn-in, from the spread of the chains'
            means); 0 runs every step.
        sampler: blackjax kernel of `estimate=mean`: `hmc` (default) or `nuts` (No-U-Turn; several times the CPU
            time of `hmc` on the real recordings, docs/benchmarks/uncertainty.md).
    """

    dim: int = 2
    loss: str = "cauchy"
    sigma_r: float = 0.2
    bias: str = "network"
    node_bias_sigma_m: float = 0.1
    n_boot: int = 32
    pair_weight: str = "none"
    summary: str = "all"
    nlos_weight: float = 0.2
    nlos_mean_m: float = 1.0
    outlier_weight: float = 0.05
    outlier_span_m: float = 50.0
    init: str = "multi"
    n_starts: int = 8
    smacof_iters: int = 300
    solver: str = "lm"
    max_steps: int = 200
    tol: float = 1e-9
    seed: int = 0
    z_up: bool = True
    irls_iters: int = 15
    gnc_stages: int = 6
    gnc_tol: float = 1e-4
    relocate_rounds: int = 2
    relocate_grid: int = 48
    relocate_candidates: int = 8
    estimate: str = "mean"
    student_nu: float = 1.0
    mcmc_chains: int = 16
    mcmc_steps: int = 4000
    mcmc_mcse: float = 0.05
    sampler: str = "hmc"

    def __check_init__(self):
        for name, allowed in (
            ("loss", LOSSES),
            ("bias", BIASES),
            ("summary", SUMMARIES),
            ("init", INITS),
            ("solver", SOLVERS),
            ("pair_weight", PAIR_WEIGHTS),
            ("estimate", ESTIMATES),
            ("sampler", SAMPLERS),
        ):
            if getattr(self, name) not in allowed:
                raise JaxcalError(
                    f"parameter {name}: expected one of {', '.join(allowed)}, got {getattr(self, name)!r}"
                )
        if self.dim not in (2, 3):
            raise JaxcalError(f"parameter dim: expected 2 or 3, got {self.dim}")
        for name in ("sigma_r", "node_bias_sigma_m", "nlos_mean_m", "outlier_span_m", "tol", "gnc_tol", "student_nu"):
            if not getattr(self, name) > 0:
                raise JaxcalError(f"parameter {name}: must be > 0, got {getattr(self, name)}")
        if not self.mcmc_mcse >= 0:
            raise JaxcalError(f"parameter mcmc_mcse: must be >= 0, got {self.mcmc_mcse}")
        for name in ("nlos_weight", "outlier_weight"):
            if not 0 <= getattr(self, name) < 1:
                raise JaxcalError(f"parameter {name}: must be in [0, 1), got {getattr(self, name)}")
        if self.nlos_weight + self.outlier_weight >= 1:
            raise JaxcalError("parameters nlos_weight + outlier_weight must be < 1")
        if (
            min(self.n_starts, self.smacof_iters, self.relocate_rounds) < 0
            or min(
                self.max_steps,
                self.irls_iters,
                self.gnc_stages,
                self.relocate_grid,
                self.n_boot,
                self.mcmc_chains,
                self.relocate_candidates,
            )
            < 1
            or self.mcmc_steps < 8
        ):
            raise JaxcalError(
                "parameters n_starts, smacof_iters, relocate_rounds must be >= 0; "
                "max_steps, irls_iters, gnc_stages, relocate_grid, relocate_candidates, n_boot, "
                "mcmc_chains >= 1; mcmc_steps >= 8"
            )


class Observations(eqx.Module):
    """Ranges as a flat list of observations between the active nodes.

    Attributes:
        i, j: (M,) node indices (into the active nodes).
        z: (M,) measured range [m].
        w: (M,) observation weight (1 per range or per pair summary).
    """

    i: Int[Array, " m"]
    j: Int[Array, " m"]
    z: Float[Array, " m"]
    w: Float[Array, " m"]


class BatchSolution(eqx.Module):
    """What `solve` returns (positions in the anchor frame; all arrays over all N nodes).

    Attributes:
        position: (N, D) [m], NaN for nodes without ranges to the frame's component.
        covariance: (N, D, D) [m^2], NaN where undefined.
        offset_m: fitted common range offset c [m] (0 with `bias=none`).
        node_offset_m: (N,) fitted per-node offsets [m] (0 unless `bias=node`; NaN for inactive nodes).
        cost: robust cost on the median summary after the multi-start fit and relocation (with the
            network offset when `bias=auto`, so that costs of runs with other starts stay comparable).
        start_costs: (S,) robust cost reached from every start.
        residual_sigma_m: weighted residual standard deviation [m].
        bias: the range offset model used (`bias=auto` resolved to `network` or `none`).
        boot_rmse_m: (2,) bootstrap position RMSE [m] of the network-offset and the no-offset fit
            (`bias=auto`; NaN otherwise).
        mcmc_accept, mcmc_rhat: `estimate=mean` only (NaN otherwise): the sampler's acceptance rate and
            the largest split R-hat over the free coordinates.
        estimate: the estimate reported: `mean`, or `map` when asked for, when the measurement graph
            makes the pair-level posterior of the nodes it fixes improper or not locally identifiable
            (`posterior_defect`, decided before any sampling; the nodes it does not fix are left out of the
            posterior and keep the fit), or when the chains did not mix (R-hat above `RHAT_MAX` or undefined).
        fallback_reason: why `estimate=mean` fell back to the fit ("" when it did not).
        model_covariance: (N, D, D) the model's own covariance (posterior sample covariance with
            `estimate=mean`, the Laplace covariance otherwise); the reported covariance is the pair-level
            covariance (`pair_covariance`) widened by the Laplace covariance (`covariance_union`) or by the
            posterior's excess over its linearisation (`posterior_excess`).
        solver_codes: outcome codes (`jaxcal.solver.outcome`) of the fit the answer rests on (the chosen
            start, relocation, offset refit or all-ranges refinement, whichever came last), then of the
            offset bootstrap's replicate fits (`bias=auto`).
        mcmc_transitions: transitions per chain the sampler ran, burn-in included (at most `mcmc_steps`;
            fewer when `mcmc_mcse` was reached first); 0 without sampling.
    """

    position: np.ndarray
    covariance: np.ndarray
    offset_m: float
    node_offset_m: np.ndarray
    cost: float
    start_costs: np.ndarray
    residual_sigma_m: float
    bias: str = "network"
    boot_rmse_m: np.ndarray = eqx.field(default_factory=lambda: np.full(2, np.nan))
    mcmc_accept: float = float("nan")
    mcmc_rhat: float = float("nan")
    estimate: str = "map"
    fallback_reason: str = ""
    model_covariance: np.ndarray | None = None
    solver_codes: np.ndarray = eqx.field(default_factory=lambda: np.zeros(0, dtype=int))
    mcmc_transitions: int = 0


def observations(range_m: np.ndarray, summary: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Flatten a (K, N, N) range stream into observations.

    Args:
        range_m: (K, N, N) ranges [m], NaN = missing.
        summary: `median`: per pair, the nanmedian over epochs of each direction, then the mean of the
            two directions (one observation per unordered pair). `all`: every finite range.

    Returns:
        (i, j, z, w): (M,) int arrays i < j for `median` (any order for `all`), ranges [m], weights.
    """
    r = np.asarray(range_m, dtype=np.float64)
    n = r.shape[1]
    if summary == "median":
        med = np.full((n, n), np.nan)
        ii, jj = np.nonzero(np.isfinite(r).any(axis=0))
        med[ii, jj] = np.nanmedian(r[:, ii, jj], axis=0)  # only columns with a finite value
        iu, ju = np.triu_indices(n, k=1)
        both = np.stack([med[iu, ju], med[ju, iu]])
        cnt = np.isfinite(both).sum(axis=0)
        pair = np.where(cnt > 0, np.nansum(both, axis=0) / np.maximum(cnt, 1), np.nan)
        ok = np.isfinite(pair)
        return iu[ok], ju[ok], pair[ok], np.ones(int(ok.sum()))
    k, ii, jj = np.nonzero(np.isfinite(r))
    ok = ii != jj
    return ii[ok], jj[ok], r[k[ok], ii[ok], jj[ok]], np.ones(int(ok.sum()))


def spread_weights(range_m: np.ndarray) -> np.ndarray:
    """Per-pair weights from the scatter of the pair's own ranges (`pair_weight=spread`).

    On real DWM1001 meshes the pairs whose ranges scatter most (over epochs, and between the i->j and
    j->i directions) are also the ones whose median is furthest from the true distance (multipath), so
    the spread is used as the pair's error scale: w = 1 / (1 + (s / s0)^2), s the standard deviation of
    the pooled ranges of both directions and s0 the median of s over all pairs (no scale to set).

    Args:
        range_m: (K, N, N) ranges [m], NaN = missing.

    Returns:
        (N, N) symmetric weights in (0, 1] (1 where a pair has a single range or s0 is 0).
    """
    r = np.asarray(range_m, dtype=np.float64)
    pooled = np.concatenate([r, np.swapaxes(r, 1, 2)], axis=0)
    cnt = np.isfinite(pooled).sum(axis=0)
    mean = np.nansum(pooled, axis=0) / np.maximum(cnt, 1)
    var = np.nansum((pooled - mean) ** 2, axis=0) / np.maximum(cnt - 1, 1)
    s = np.where(cnt > 1, np.sqrt(var), np.nan)
    off = ~np.eye(r.shape[1], dtype=bool) & np.isfinite(s)
    s0 = float(np.median(s[off])) if off.any() else 0.0
    if not s0 > 0:
        return np.ones(r.shape[1:])
    return np.where(np.isfinite(s), 1.0 / (1.0 + (s / s0) ** 2), 1.0)
