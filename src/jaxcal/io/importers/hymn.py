"""Importer of the HYMN dataset's UWB part (TU Dresden, Torgau hall; CC BY 4.0) -> `TrajectoryDataset`.

Input: the dataset root (the folder holding `data/`), read from
`data/processed/csv/uwb.csv` (point_id, ts [Unix ms], anchor_ids and ranges as Python-list strings,
ranges in m, `nan` = failed exchange), `data/reference/csv/anchor_coordinates.csv` (X/Y/Z_LOCAL of
each anchor; the UWB ones are UWB_01..UWB_10) and `data/reference/csv/point_coordinates.csv`
(X/Y/Z_LOCAL_UWB2: the UWB tag antenna on the measurement plate at each surveyed point).

Model: one tag (`UWB2`, lever arm zero: the body origin is the tag antenna). The tag stands still at
one surveyed point per dwell (a maximal run of consecutive rows, in time order, with the same
point_id). Poses must be strictly increasing in time, so each dwell becomes two poses at the same
position: at the dwell's first and last range time (one pose for a one-row dwell). Between dwells
the platform moved along an unknown path; no range lies there, so interpolating across the gap
never produces a range prediction. Times are Unix seconds (ts / 1000).

Skipped and counted (in `description`): failed exchanges (`nan`), rows that cannot be parsed,
list length mismatches, points without coordinates, negative ranges.

Source: github.com/TUD-ITVS/HYMN-dataset @ 39fdafc; Ammad et al., IEEE Data Descriptions 2026,
doi:10.1109/IEEEDATA.2026.3691044. Licence: CC BY 4.0 (dataset).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from jaxcal.data import TrajectoryDataset
from jaxcal.errors import JaxcalError
from jaxcal.io.importers._common import (
    BadCell,
    Skipped,
    csv_rows,
    existing_dir,
    existing_file,
    finite,
    join_notes,
    num,
)

__all__ = ["import_hymn", "UWB_CSV", "ANCHORS_CSV", "POINTS_CSV", "TAG_ID"]

UWB_CSV = "data/processed/csv/uwb.csv"
ANCHORS_CSV = "data/reference/csv/anchor_coordinates.csv"
POINTS_CSV = "data/reference/csv/point_coordinates.csv"
TAG_ID = "UWB2"
SOURCE = (
    "HYMN dataset, TU Dresden ITVS (github.com/TUD-ITVS/HYMN-dataset @ 39fdafc; "
    "Ammad et al., IEEE Data Descriptions 2026, doi:10.1109/IEEEDATA.2026.3691044; "
    "Zenodo 10.5281/zenodo.17979434)"
)
LICENSE = "CC BY 4.0 (attribution: HYMN dataset, TU Dresden)"


def _pylist(cell: str, column: str) -> list[str]:
    s = cell.strip()
    if not (s.startswith("[") and s.endswith("]")):
        raise BadCell(column, cell, "not a list")
    inner = s[1:-1].strip()
    return [v.strip().strip("'\"") for v in inner.split(",")] if inner else []


def _coordinates(path: Path, xyz: tuple[str, str, str]) -> dict[str, tuple[float, float, float]]:
    cols, rows = csv_rows(path, ("point_id", *xyz))
    ix = [cols.index(c) for c in ("point_id", *xyz)]
    out: dict[str, tuple[float, float, float]] = {}
    skipped = Skipped(path)
    for line, row in rows:
        try:
            if len(row) != len(cols):
                raise BadCell("point_id", "", f"expected {len(cols)} fields, got {len(row)}")
            x, y, z = (finite(row[i], c) for i, c in zip(ix[1:], xyz, strict=True))
            out[row[ix[0]].strip()] = (x, y, z)
        except BadCell as e:
            skipped.add("bad row", line, str(e))
    skipped.fail_if_nothing(len(out))
    return out


def import_hymn(root: str | os.PathLike, name: str | None = None) -> TrajectoryDataset:
    """Read HYMN's UWB measurements at the surveyed points into a trajectory dataset.

    Args:
        root: the dataset root (the folder holding `data/`).
        name: dataset name; default "hymn-torgau".

    Returns:
        `TrajectoryDataset`: anchors UWB_* with surveyed truth (A, 3), one tag with zero lever arm,
        two poses per dwell, one range per (row, anchor) with a finite value.
    """
    r = existing_dir(root)
    uwb = existing_file(r / UWB_CSV)
    anchors_xyz = _coordinates(existing_file(r / ANCHORS_CSV), ("X_LOCAL", "Y_LOCAL", "Z_LOCAL"))
    points = _coordinates(existing_file(r / POINTS_CSV), ("X_LOCAL_UWB2", "Y_LOCAL_UWB2", "Z_LOCAL_UWB2"))
    anchor_ids = sorted(a for a in anchors_xyz if a.startswith("UWB_"))
    if not anchor_ids:
        raise JaxcalError(f"{r / ANCHORS_CSV}: no UWB_* anchor")
    a_idx = {a: i for i, a in enumerate(anchor_ids)}

    cols, rows = csv_rows(uwb, ("point_id", "ts", "anchor_ids", "ranges"))
    ip, it, ia, ir = (cols.index(c) for c in ("point_id", "ts", "anchor_ids", "ranges"))
    skipped = Skipped(uwb)
    epochs = []  # (time_s, point_id, [(anchor index, range)])
    n_failed = n_unknown_anchor = 0
    for line, row in rows:
        try:
            if len(row) != len(cols):
                raise BadCell("ts", "", f"expected {len(cols)} fields, got {len(row)}")
            pid = row[ip].strip()
            if pid not in points:
                skipped.add("point without coordinates", line, f"point_id {pid!r} not in {POINTS_CSV}")
                continue
            t = finite(row[it], "ts") / 1000.0
            ids = _pylist(row[ia], "anchor_ids")
            vals = [num(v, "ranges") for v in _pylist(row[ir], "ranges")]
            if len(ids) != len(vals):
                raise BadCell("ranges", row[ir], f"{len(vals)} ranges for {len(ids)} anchors in")
            if any(v < 0 for v in vals):
                raise BadCell("ranges", row[ir], "negative range in")
        except BadCell as e:
            skipped.add("unparsable row", line, str(e))
            continue
        meas = []
        for a, v in zip(ids, vals, strict=False):
            if v != v:
                n_failed += 1
            elif a not in a_idx:
                n_unknown_anchor += 1
            else:
                meas.append((a_idx[a], v))
        epochs.append((t, pid, meas))
    skipped.fail_if_nothing(len(epochs))
    epochs.sort(key=lambda e: e[0])  # stable: rows with equal ts keep file order

    pose_t, pose_p, dwells = [], [], 0
    prev_pid = None
    for k, (t, pid, _) in enumerate(epochs):
        last_of_dwell = k + 1 == len(epochs) or epochs[k + 1][1] != pid
        if pid != prev_pid:
            dwells += 1
            pose_t.append(t)
            pose_p.append(points[pid])
        elif last_of_dwell and t > pose_t[-1]:
            pose_t.append(t)
            pose_p.append(points[pid])
        prev_pid = pid
    pose_time = np.asarray(pose_t)
    if pose_time.size >= 2 and np.any(np.diff(pose_time) <= 0):
        i = int(np.argmax(np.diff(pose_time) <= 0))
        raise JaxcalError(f"{uwb}: two dwells share the time {pose_time[i]!r} s; cannot form strictly increasing poses")

    rt = [t for t, _, meas in epochs for _ in meas]
    ra = [a for _, _, meas in epochs for a, _ in meas]
    rv = [v for _, _, meas in epochs for _, v in meas]
    notes = [
        f"HYMN UWB: {len(epochs)} epochs at {len(set(e[1] for e in epochs))} surveyed points ({dwells} dwells, "
        f"2 poses each at the dwell's first and last range time), {len(rv)} ranges, {len(anchor_ids)} anchors",
        f"{n_failed} failed exchange(s) (nan) not imported",
        f"{n_unknown_anchor} range(s) to anchors without coordinates dropped" if n_unknown_anchor else "",
        skipped.describe(),
    ]
    return TrajectoryDataset(
        name=name or "hymn-torgau",
        anchor_ids=tuple(anchor_ids),
        tag_ids=(TAG_ID,),
        lever_arm=np.zeros((1, 3)),
        pose_time=pose_time,
        pose_position=np.asarray(pose_p, float).reshape(-1, 3),
        range_time=np.asarray(rt, float),
        range_anchor=np.asarray(ra, np.int32),
        range_tag=np.zeros(len(rv), np.int32),
        range=np.asarray(rv, np.float32),
        anchor_truth=np.asarray([anchors_xyz[a] for a in anchor_ids], float),
        description=join_notes(*notes),
        source=SOURCE,
        license=LICENSE,
    )
