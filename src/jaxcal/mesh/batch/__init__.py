"""Robust batch calibration of a static mesh (`--method batch`); see `jaxcal.mesh.batch.driver`."""

from jaxcal.mesh.batch.driver import *  # noqa: F403
from jaxcal.mesh.batch.driver import (  # noqa: F401
    _cost,
    _fit_starts,
    _irls_weight,
    _Numbers,
    _procrustes_rmse,
    _range_weights,
    _residuals,
    _rho_of,
    _rows,
    _solver,
    _split_rhat,
    _sqrt_rho_of,
    _State,
    covariance_union,
    offset_bootstrap,
    posterior_defect,
    posterior_excess,
    posterior_mean,
    spread_weights,
    stage_count,
    warn_if_unmixed,
)
