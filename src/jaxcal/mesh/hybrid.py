"""`pgp+batch`: PGP for global, multimodal, outlier-tolerant placement, then the robust batch refinement.

PGP (eq. 3-14) runs over every epoch and gives each node's final posterior; its final estimates (and their
mirror image) are added as extra starts to the batch solver's MDS / SMACOF multi-start (`batch.solve`), which
keeps the start with the lowest robust cost. Adding starts can only lower the batch cost, so the refinement
never ends in a worse optimum of its own objective than batch alone; whether it also lowers the error
against truth is measured (benchmarks/peers.py), not assumed.

The result keeps PGP's per-epoch track (`track/*`) and reports the refined final positions and the batch
covariance (`position`, `covariance`): with batch's default `estimate=mean`, the posterior mean sampled
around that optimum (`batch.posterior_mean`) and the pair-level covariance at it, widened where that
posterior is curved (`batch.posterior_excess`).

Parameters: keys prefixed `pgp.` or `batch.` go to that stage (e.g. `--set pgp.cell_m=0.25 --set
batch.loss=huber`); an unprefixed key goes to every stage that knows it (e.g. `sigma_r`), and is an error if
neither does.

Nodes the measured graph cannot fix in the frame (`identify.py`) are NaN rows with one warning line; a frame
the ranges do not determine gives a0 alone, without running either stage.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import equinox as eqx
import numpy as np

from jaxcal.data import MeshDataset, Result
from jaxcal.errors import JaxcalError
from jaxcal.mesh import batch, pgp
from jaxcal.params import as_dict, with_overrides

__all__ = ["split_params", "calibrate"]


def split_params(params: Mapping[str, Any] | None) -> tuple[dict[str, Any], dict[str, Any]]:
    """Overrides for the PGP and batch stages from one flat mapping (see the module docstring)."""
    pgp_keys = set(as_dict(pgp.PGPParams()))
    batch_keys = set(as_dict(batch.BatchParams()))
    out_p: dict[str, Any] = {}
    out_b: dict[str, Any] = {}
    for key, value in (params or {}).items():
        stage, dot, name = key.partition(".")
        if dot and stage in ("pgp", "batch"):
            (out_p if stage == "pgp" else out_b)[name] = value
            continue
        known = False
        if key in pgp_keys:
            out_p[key] = value
            known = True
        if key in batch_keys:
            out_b[key] = value
            known = True
        if not known:
            raise JaxcalError(
                f"unknown parameter {key!r} for pgp+batch (use pgp.KEY or batch.KEY; see --method pgp / batch)"
            )
    return out_p, out_b


def calibrate(dataset: MeshDataset, params=None, config: str | None = None) -> Result:
    """`--method pgp+batch`: PGP track, then robust batch refinement of the final positions.

    Args:
        dataset: a `MeshDataset`.
        params: overrides (`pgp.KEY`, `batch.KEY`, or unprefixed keys known to either stage).
        config: frame configuration name.

    Returns:
        A `Result`: refined `position` and `covariance`, PGP's per-epoch track.
    """
    from jaxcal import __version__
    from jaxcal.mesh import masking

    p_over, b_over = split_params(params)
    b = with_overrides(batch.BatchParams(), b_over)
    anchors = dataset.config(config)
    empty = masking.undetermined_frame_result(dataset, anchors, "pgp+batch", b.dim)
    if empty is not None:  # the ranges do not fix the frame: nothing to fit (one warning line)
        return empty
    # the track and final positions only: PGP's posterior grids (with node-local grids an (N, n, n)
    # array over the whole site) are never read here
    res_pgp, _ = pgp.run_pgp(dataset, p_over, config, posterior=False)
    sol = batch.solve(dataset.range, anchors, b, dataset.node_ids, extra_starts=res_pgp.position[None])
    batch.warn_if_unmixed(sol, b)
    outcome = batch.check_solver(sol, b, "pgp+batch")
    # record what was used: bias=auto resolved, estimate=mean or its fallback to the fit
    b = eqx.tree_at(lambda q: (q.bias, q.estimate), b, (sol.bias, sol.estimate))
    position = sol.position
    covariance = sol.covariance
    # Nodes the batch fit cannot place (not connected to a0) keep the PGP estimate and covariance.
    missing = ~np.isfinite(position).all(axis=1)
    if missing.any() and position.shape[1] == res_pgp.position.shape[1]:
        position = position.copy()
        position[missing] = res_pgp.position[missing]
        if res_pgp.covariance is not None:
            covariance = covariance.copy()
            covariance[missing] = res_pgp.covariance[missing]
    track_position = res_pgp.track_position
    if track_position is not None and track_position.shape[-1] != position.shape[1]:
        track_position = None  # a 3-D refinement has no 2-D track to keep
    res = Result(
        ids=dataset.node_ids,
        position=position,
        method="pgp+batch",
        dataset=dataset.name,
        frame="anchors:" + ",".join(str(a) for a in anchors),
        params={
            **{f"pgp.{k}": v for k, v in res_pgp.params.items()},
            **{f"batch.{k}": v for k, v in {**as_dict(b), **outcome.params()}.items()},
        },
        covariance=covariance,
        track_time=res_pgp.track_time if track_position is not None else None,
        track_position=track_position,
        software=f"jaxcal {__version__}",
    )
    return masking.mask_result(res, dataset.range)  # what the ranges cannot fix: NaN rows + a warning
