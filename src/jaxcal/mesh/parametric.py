"""Parametric baseline of paper 000, eq. (9): the grid filter with point-estimate neighbours.

Same grid, regions, motion update, estimate and parameters as PGP (`pgp`), but each neighbour j
enters the likelihood of eq. (11) as ONE hypothesis, its eq. (13) estimate, with the range std
widened
by its posterior covariance: `sigma_ij = sigma_r + sqrt(tr P_j)` (eq. 9). The receiver's own
uncertainty is its grid, so its trace is not added again. `P_j` is the covariance of j's whole grid
posterior (so a multimodal neighbour gets a wide, not a wrong, constraint). `tau` and `max_hyp` are
unused.
"""

from __future__ import annotations

from jaxcal.data import MeshDataset, Result
from jaxcal.mesh.pgp import PGPParams, run_pgp

__all__ = ["calibrate", "PGPParams"]


def calibrate(dataset: MeshDataset, params=None, config: str | None = None, progress=None) -> Result:
    """`--method parametric`: the grid filter with eq. (9) point-estimate likelihoods; nodes the ranges
    cannot fix in the frame (`identify.py`) are NaN rows, named in one warning line.

    `progress`: optional callback called with the epochs done since its last call."""
    from jaxcal.mesh.identify import mask_result

    return mask_result(run_pgp(dataset, params, config, mode="parametric", progress=progress)[0], dataset.range)
