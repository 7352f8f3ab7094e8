"""Robust batch calibration of a static mesh: all epochs at once, robust loss, range bias, covariance.

Model: the measured range of pair (i, j) is `z_ij = ||p_i - p_j|| + c + b_i + b_j + e_ij`, with a common
range offset `c` (`bias="network"`; DWM1001 ranges are typically 0.1-0.3 m short, so `c < 0`), optional
per-node offsets `b_i` (`bias="node"`, antenna delays, with a Gaussian prior of width
`node_bias_sigma_m`) and an error `e` scored by a robust loss rho (Huber, Cauchy, or the negative log of
a LOS / NLOS / outlier mixture). The fit minimises `sum rho(e)` with Optimistix least squares
(Levenberg-Marquardt or Gauss-Newton) on "square-root" residuals `sign(e) sqrt(2 rho(e))`, whose
Gauss-Newton gradient equals the gradient of the robust cost.

`bias="auto"` fits the network offset and then keeps it only if a residual bootstrap predicts a smaller
position error with it than without (`offset_bootstrap`): in weak geometries (nearly planar 3-D scenes) the
offset trades off against the poorly determined directions, and its estimate can cost more than it removes.

Observations are either one robust summary per pair (`summary="median"`: the median over epochs of
each direction, then the mean of the two directions) or every single range (`summary="all"`).

A local fit needs a global start: classical MDS of the distance matrix completed by shortest paths,
SMACOF from it, and SMACOF from several random starts are all refined (vmapped) and the one with the
lowest robust cost wins. A global mirror image has the same cost (it is the gauge, fixed at the end by
`to_frame`); partial flips of weakly connected nodes are what the random starts are for.

Reported estimate (`estimate`): by default the posterior *mean* of the positions (`posterior_mean`), not
the fit itself (the posterior mode, `estimate=map`). In a weak geometry the two differ and the mean is the
one with the least expected squared error. It is sampled from a model where the pair, not the single
range, is the unit of information (repeated ranges of one pair share its systematic error).

Only the nodes that the measurement graph fixes in the frame (`jaxcal.mesh.identify`) and the ranges between
them enter the covariance and the posterior: a node that ranges one or two others would make the Hessian
singular (or the posterior improper) for every node. The others keep the fit's position, which
`calibrate` turns into a NaN row with one warning line. A frame with a mirror image (a frame node ranging only
D fixed nodes) leaves only the frame's measured triangle fixed (`identify`): the others are NaN rows too.

Output frame: a0 at the origin, a1 on +x, a2 with y > 0 (CONTRACT 1.1). Covariances are computed in
gauge-fixed coordinates of that frame, so they are exactly zero for the coordinates the frame fixes. The
reported covariance rests on the covariance under per-pair systematic errors whose size is estimated
from the pair residuals (`jaxcal.mesh.pair_covariance`: every pair counted once whatever the number of
epochs, with the part of its error that the geometry absorbs accounted for): with `estimate=map` it
widens the Laplace covariance `sigma^2 (J^T W J)^-1` of the all-ranges fit (W = IRLS weights psi(e)/e)
in every direction (`covariance_union`); with `estimate=mean` the posterior's excess over its own
linearisation is added to it (`posterior_excess`: the width of a curved, weakly determined posterior,
which a linearised covariance cannot see; ~0 where the ranges fix the nodes to first order; measured
against the posterior's median width over its linearisation, `fisher_ratio`, not the Student-t's
asymptotic ratio, which a sparse network's posterior exceeds in every direction).

Modules (one job each; the names below are re-exported here, `from jaxcal.mesh import batch` is the entry):
`params` (`BatchParams`, observations), `problem` (the validated range stream), `model` (losses, state,
residuals), `fit` (starts, graduated multi-start fit, relocation moves, IRLS), `bootstrap` (`bias=auto`),
`covariance` (Laplace and pair-level covariance, `covariance_union`, `posterior_excess`), `sampler`
(`posterior_mean`, `posterior_defect`) and `driver` (`solve` as named stages, `calibrate`).
"""

# Besides `__all__`, private names that the tests of the model, the fit and the sampler reach as `batch._X`
# (pyproject.toml: F401 is off for this file, which only re-exports).
from jaxcal.mesh.batch.bootstrap import _procrustes_rmse, offset_bootstrap
from jaxcal.mesh.batch.covariance import _range_weights, covariance_union, posterior_excess
from jaxcal.mesh.batch.driver import calibrate, check_solver, solve, stage_count, warn_if_unmixed
from jaxcal.mesh.batch.fit import _fit_starts, _solver
from jaxcal.mesh.batch.model import _cost, _irls_weight, _Numbers, _residuals, _rho_of, _rows, _sqrt_rho_of, _State
from jaxcal.mesh.batch.params import (
    BIASES,
    ESTIMATES,
    INITS,
    LOSSES,
    PAIR_WEIGHTS,
    RHAT_MAX,
    SAMPLERS,
    SOLVERS,
    SUMMARIES,
    BatchParams,
    BatchSolution,
    Observations,
    observations,
    spread_weights,
)
from jaxcal.mesh.batch.sampler import _split_rhat, posterior_defect, posterior_mean

__all__ = [
    "BatchParams",
    "Observations",
    "BatchSolution",
    "observations",
    "spread_weights",
    "solve",
    "stage_count",
    "check_solver",
    "warn_if_unmixed",
    "calibrate",
    "offset_bootstrap",
    "covariance_union",
    "posterior_excess",
    "posterior_mean",
    "posterior_defect",
    "LOSSES",
    "BIASES",
    "SUMMARIES",
    "INITS",
    "SOLVERS",
    "PAIR_WEIGHTS",
    "ESTIMATES",
    "SAMPLERS",
    "RHAT_MAX",
]
