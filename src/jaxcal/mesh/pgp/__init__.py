"""PGP: the grid-based Bayesian self-calibration filter of paper 000 (Section III, eq. 3-14).

Nodes are reordered so that the configuration's (a0, a1, a2) come first. Every node has a log posterior
on one common square grid (`grid.py`), all of them one batched array `(nodes, nx, ny)`; a0 is the origin
cell, a1's region is the positive x axis (the 1-D histogram of eq. 5), a2's the half plane y >= 0
(eq. 6). Per epoch and node: motion update over the `top_k` most probable cells (eq. 7-8), the
hypothesis-weighted likelihood of every neighbour with a range (eq. 10-11), the posterior in log space
(eq. 12), the estimate within `r_est` of the MLE cell (eq. 13), optional smoothing (eq. 14). Epochs run
in one `lax.scan` inside one jitted function; numbers are arrays, so changing them never recompiles.

Choices the paper leaves open (documented here, recorded in the result's `params`):

- Ranges: the mean of i->j and j->i when both exist, else the one that exists; missing = no factor.
- Neighbours: a1 uses a0 only (eq. 5), a2 uses a0 and a1 (eq. 6; `a2_all=True` lets it use every node),
  the others every node. A neighbour contributes hypotheses only once it is *localised*: it has received
  ranges from at least `min_refs` distinct localised neighbours (a1: a0; a2: a0 and a1), so a node
  whose posterior is still a ring around one reference does not spread a random arc of that ring as
  hypotheses. A node's estimate is reported (available) from the epoch it is localised.
- Motion update only for localised nodes; before that the posterior accumulates likelihoods exactly
  (a static prior), because truncating a ring to `top_k` cells would lock in a random arc.
- Hypotheses: the smallest set of most probable cells holding mass `tau`, capped at `max_hyp` cells.
- `sigma_v` is the std of the transition distance of eq. (8) in metres per epoch; `v * dt` with dt the
  epoch time step.
- `update_order`: "jacobi" (default) updates every node from the previous epoch's posteriors: the
  result does not depend on node labels. "gauss-seidel" updates a1, a2, then the others in index order,
  each using the newest posteriors of the nodes before it (order-dependent, localises in fewer epochs).

Beyond the paper (issue #18): when a frame pair (a0-a1, a0-a2, a1-a2) is never measured, or only late,
the paper's rule never localises a1 (or a2) and hence nothing after it, although the network may fix
every node. `frame="auto"` (default) then runs the filter in the frame of the best-connected,
best-conditioned triple whose pairs are measured (`frame_choice.filter_frame`) and moves every epoch's
estimates into the configuration's frame through that epoch's a0, a1, a2 estimates (the final
covariance to first order, `frame.frame_covariance`); `PGPInfo.frame` names the grids' frame. Where the
configuration's pairs are measured early the filter is the paper's, unchanged. `calibrate` then sets the
nodes the measured graph cannot fix (`identify.py`) to NaN rows, with one warning line.

Defaults (`PGPParams`): 0.5 m cells, at most 8 hypotheses, `likelihood="window"`: the fast path
of `fast.py`. Until every node is localised (the first few epochs) and whenever the mass could
leave a window, an epoch is the direct evaluation on every cell; otherwise every node's epoch runs
on a W x W window around its mass (10 m a side) and a1 on its row, with a proven bound (< e^-30)
on the posterior mass outside, so the answers equal the direct evaluation (`likelihood="direct"`,
kept as the reference) up to rounding. `run_pgp` drives the scan from the host in chunks
(`run_chunked`): windowed chunks do not carry the full grid. `filter_epochs` (one scan, used by
tuning and sweeps) computes the same epochs. Speed: `benchmarks/pgp_speed.py` (figures on the
benchmarks page of the docs, "PGP speed"). `start`/`advance` feed epochs as they arrive (live
calibration); chunks equal one run.

Large sites (issue #26): the one grid grows with the site's area, so at constant density its cost
grows as N^2 and `extent_m` cuts off nodes beyond 60 m. `grid_mode="auto"` (default) runs such sites
(the full grid wider than one node-local grid, i.e. the site wider than radio range) on node-local grids
(`local.py`): the same epochs where each node's mass lies in its own grids (tested), at a cost that
follows the measured pairs, with a stricter localisation rule (`localise_m`). Sites within radio range
(torgau and the other small recordings) run on the one grid as before.

The filter API (what tuning, sweeps, the lockstep batch and the checkpointed segments build on):
`prepare` (dataset -> `FilterConfig`, `FilterParams`, `FilterInputs`, initial log posteriors, node
order), `init_state`, `scan` / `run_scan` (epochs from a state), `scan_windows` (windowed epochs
only), `filter_epochs` / `run_filter` (the whole filter), `run_chunked` / `advance_chunked` /
`run_segmented` (host-driven), `full_state` / `full_logpost`, `node_order`, `neighbour_sets`.

Modules (one job each; the names below are re-exported here, `from jaxcal.mesh import pgp` is the entry):
`params` (`PGPParams`, `validate_params`), `state` (the filter's pytrees, `PGPInfo`), `kernels`
(hypotheses, one node's epoch, the window step `WindowStep`), `epochs` (the epoch scans and their
drivers), `setup` (ranges, neighbour sets, node order, `prepare`), `stream` (`PGPStream`, `start`,
`advance`), `mirror` (after the filter: parts locked in a mirror image moved to the image the ranges prefer,
undecided images spanned by the covariance; `PGPParams.mirror`) and `driver` (`run_pgp`, the range-offset
pass, node-local runs, `calibrate`, `with_pair_covariance`).
"""

from jaxcal.mesh.pgp.driver import (
    calibrate,
    cell_variance,
    global_grid_only,
    local_setup,
    local_site,
    run_pgp,
    software_version,
    uses_local,
    with_pair_covariance,
)
from jaxcal.mesh.pgp.epochs import (
    advance_chunked,
    filter_epochs,
    run_chunked,
    run_filter,
    run_scan,
    run_segmented,
    scan,
    scan_windows,
)
from jaxcal.mesh.pgp.kernels import WindowStep
from jaxcal.mesh.pgp.params import (
    BIASES,
    FRAMES,
    GRID_MODES,
    LIKELIHOODS,
    MIRRORS,
    NUMERIC,
    OFFSET_EPOCHS,
    RANGE_MODELS,
    PGPParams,
    validate_params,
)
from jaxcal.mesh.pgp.setup import filter_params, neighbour_sets, node_order, prepare, symmetric_ranges
from jaxcal.mesh.pgp.state import (
    FilterConfig,
    FilterInputs,
    FilterOut,
    FilterParams,
    FilterState,
    PGPInfo,
    full_logpost,
    full_state,
    init_state,
)
from jaxcal.mesh.pgp.stream import PGPStream, advance, start, stream_posterior

__all__ = [
    "PGPParams",
    "PGPInfo",
    "PGPStream",
    "run_pgp",
    "calibrate",
    "with_pair_covariance",
    "start",
    "advance",
    "stream_posterior",
    "symmetric_ranges",
    "validate_params",
    "uses_local",
    "local_site",
    "local_setup",
    "global_grid_only",
    "cell_variance",
    "software_version",
    # the filter API
    "FilterConfig",
    "FilterParams",
    "FilterInputs",
    "FilterState",
    "FilterOut",
    "WindowStep",
    "prepare",
    "filter_params",
    "node_order",
    "neighbour_sets",
    "init_state",
    "full_state",
    "full_logpost",
    "scan",
    "run_scan",
    "scan_windows",
    "filter_epochs",
    "run_filter",
    "run_chunked",
    "advance_chunked",
    "run_segmented",
    "BIASES",
    "MIRRORS",
    "FRAMES",
    "GRID_MODES",
    "LIKELIHOODS",
    "NUMERIC",
    "OFFSET_EPOCHS",
    "RANGE_MODELS",
]
