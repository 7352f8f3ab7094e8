"""Parametric baseline of paper 000, eq. (9): the grid filter with point-estimate neighbours.

Same grid, regions, motion update, estimate and parameters as PGP (`pgp`), but each neighbour j
enters the likelihood of eq. (11) as ONE hypothesis, its eq. (13) estimate, with the range std
widened
by its posterior covariance: `sigma_ij = sigma_r + sqrt(tr P_j)` (eq. 9). The receiver's own
uncertainty is its grid, so its trace is not added again. `P_j` is the covariance of j's whole grid
posterior (so a multimodal neighbour gets a wide, not a wrong, constraint). `tau` and `max_hyp` are
unused.

Its covariance is reported as pgp's is (`pgp.with_pair_covariance`): the grid posterior's, widened in every
direction to at least the covariance under per-pair systematic errors sized from the data, plus the node's
displacement from a robust fit of the pair ranges. The grid posterior alone multiplies every epoch's
likelihood as if independent and holds a point-estimate neighbour's error as noise: on the random families
its ellipses missed nodes metres off (NEES/dof up to 200).
"""

from __future__ import annotations

from jaxcal.data import MeshDataset, Result
from jaxcal.mesh.pgp import PGPParams, run_pgp, with_pair_covariance

__all__ = ["calibrate", "PGPParams"]


def calibrate(dataset: MeshDataset, params=None, config: str | None = None, progress=None) -> Result:
    """`--method parametric`: the grid filter with eq. (9) point-estimate likelihoods; nodes the ranges
    cannot fix in the frame (`identify.py`) are NaN rows, named in one warning line.

    `progress`: optional callback called with the epochs done since its last call."""
    from jaxcal.mesh.masking import mask_result

    res = run_pgp(dataset, params, config, mode="parametric", progress=progress, posterior=False)[0]
    return mask_result(with_pair_covariance(res, dataset.range), dataset.range)
