"""Cross-checks of what a file joins: ranges against the layout (truth) they are stored with.

An importer joins two sources (a folder of range files and a layout file, ranges and a motion-capture
log); a wrong pair still gives a well-formed file, and every later evaluation is then scored against
another site. `truth_consistency` measures the join: the median of |range - layout distance| over every
measurement, and the ids on one side only. Measured on the shared recordings (`jaxcal stats`, all
ranges): right pairs give medians of 0.11-0.27 m (dwm1001 srvlab_ground 0.11, 3D_distribution 0.13,
campus_sport 0.27, hymn-torgau 0.27, cuhksz 0.17, hanyang 0.13-0.14); the six wrong dwm1001
range/layout pairs give 1.53-7.56 m. `LAYOUT_MISMATCH_M` sits between, at "a few tenths of a metre".
"""

from __future__ import annotations

LAYOUT_MISMATCH_M = 0.5


def truth_consistency(ds) -> dict | None:
    """How well the truth of a mesh or trajectory dataset explains its ranges; None without truth.

    Returns:
        {"median_m": median |range - true distance| [m] (NaN when no range has truth on both ends),
         "ranges": ranges compared, "no_ranges": ids with truth that never ranged,
         "no_truth": ids that ranged but have no truth (allowed: NaN truth = unknown),
         "problems": one line per problem found}.
    """
    import numpy as np

    from jaxcal.metrics import ranging_errors

    if hasattr(ds, "node_ids"):
        truth, ids = ds.truth, list(ds.node_ids)
        if truth is None or not np.isfinite(truth).all(axis=1).any():
            return None
        m = np.isfinite(ds.range)
        ranged = m.any(axis=(0, 1)) | m.any(axis=(0, 2))
        what = "node"
    else:
        truth, ids = ds.anchor_truth, list(ds.anchor_ids)
        if truth is None or not np.isfinite(truth).all(axis=1).any():
            return None
        ranged = np.bincount(ds.range_anchor[np.isfinite(ds.range)], minlength=len(ids)) > 0
        what = "anchor"
    known = np.isfinite(truth).all(axis=1)
    err, _ = ranging_errors(ds)
    median = float(np.median(np.abs(err))) if err.size else float("nan")
    no_ranges = [i for i, k, r in zip(ids, known, ranged, strict=True) if k and not r]
    no_truth = [i for i, k, r in zip(ids, known, ranged, strict=True) if r and not k]
    problems = []
    if err.size == 0:
        problems.append(f"no range has a true distance (the layout's {what} ids match none of the ranges)")
    elif median > LAYOUT_MISMATCH_M:
        problems.append(
            f"median |range - layout distance| is {median:.2f} m over {err.size} ranges (above "
            f"{LAYOUT_MISMATCH_M} m): the layout does not fit the ranges (another site, or a wrong id order?)"
        )
    if no_ranges:
        problems.append(f"{what}(s) in the layout without any range: {', '.join(no_ranges)}")
    return {
        "median_m": median,
        "ranges": int(err.size),
        "no_ranges": no_ranges,
        "no_truth": no_truth,
        "problems": problems,
    }
