"""Linear least-squares multilateration of each anchor (the `ls` baseline, "one-key calibration").

The multilateration itself (`common.multilaterate`: the linear system, its planar variant and its
covariance) is shared with `nls` (its start) and `poses` (the clock-offset search); this module is the
method: its parameters and `calibrate`.
"""

from __future__ import annotations

import jax

from jaxcal.data import Result
from jaxcal.params import with_overrides
from jaxcal.precision import in_float64
from jaxcal.trajectory.common import TrajectoryParams, finish, multilaterate_all
from jaxcal.trajectory.nls import prepare_offset

__all__ = ["LSParams", "calibrate"]


class LSParams(TrajectoryParams):
    """Parameters of `ls`: only the shared `TrajectoryParams` settings."""


@in_float64
def calibrate(dataset, params=None, config=None) -> Result:
    """`--method ls`: linear least-squares multilateration of every anchor (frame `world`).

    Args:
        dataset: TrajectoryDataset. params: overrides of `LSParams`. config: ignored.

    Returns:
        Result with `position` (A, 3) and `covariance` (A, 3, 3); NaN for anchors with too few ranges.
    """
    p = with_overrides(LSParams(), params)
    groups, info = prepare_offset(dataset, p)
    est, cov = jax.jit(multilaterate_all, static_argnums=(3, 4, 5))(
        groups.position, groups.range, groups.mask, p.planar_tol_m, p.side, p.planar_ratio
    )
    return finish(dataset, "ls", p, groups, est, cov, info)
