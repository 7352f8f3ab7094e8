"""Importer of the Hanyang outdoor UWB dataset (ADIP lab, Hanyang University; Apache-2.0) -> trajectory.

Input: one run folder (e.g. `LOS/Trajectory_A/Case_1`) holding `A<id>.csv` per anchor (rostopic
csv: `%time`, `field.stamp` [ns], `field.id`, `field.x/y/z` = the anchor's configured position [m],
`field.distanceFromTag` [m], `field.rssi`, `field.rssi_fp` [dBm]; ~10 Hz) and `trajectory.csv`
(`timestamp` [ns], `x, y, z` [m, local], `heading_degrees`; RTK-GNSS reference, ~8 Hz).

Model: anchors `A<id>` (file stems, sorted by id) with truth = the median of their configured
position column (constant in the files); one tag `tag` with zero lever arm (the reference is the
tag's position; the heading is not imported since a zero lever arm makes it irrelevant); poses = the
RTK trajectory. Range time = `field.stamp` / 1e9 (Unix seconds, the clock of `trajectory.csv`).
`ranges/los` = 1 for every range when the nearest folder named LOS or NLOS above the run folder is
`LOS`, 0 for `NLOS`, -1 when there is none. `fp_rssi` / `rx_rssi` = `field.rssi_fp` / `field.rssi`.

Skipped and counted (in `description`): unparsable rows, non-positive ranges, ranges outside the
reference trajectory's time span (cannot be interpolated), trajectory rows whose time does not
increase.

Source: github.com/cucudasluv/UWB-dataset @ c125998 (Zenodo 10.5281/zenodo.15226105). Licence: Apache-2.0.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from jaxcal.data import TrajectoryDataset
from jaxcal.errors import JaxcalError
from jaxcal.io.importers._common import BadCell, Skipped, csv_rows, existing_dir, existing_file, finite, join_notes, num

__all__ = ["import_hanyang", "los_label"]

SOURCE = (
    "Hanyang University ADIP lab outdoor UWB dataset (github.com/cucudasluv/UWB-dataset "
    "@ c12599812e556324eadc763e409ea8f51098dda6; Zenodo 10.5281/zenodo.15226105)"
)
LICENSE = "Apache-2.0"
_ANCHOR_FILE = re.compile(r"^A(\d+)\.csv$")
_ANCHOR_COLS = ("field.stamp", "field.x", "field.y", "field.z", "field.distanceFromTag")


def los_label(run_dir: str | os.PathLike) -> int:
    """1 if the nearest LOS/NLOS folder above (or at) `run_dir` is LOS, 0 if NLOS, -1 if none."""
    for part in reversed(Path(run_dir).resolve().parts):
        if part.upper() == "LOS":
            return 1
        if part.upper() == "NLOS":
            return 0
    return -1


def _read_anchor(p: Path):
    cols, rows = csv_rows(p, _ANCHOR_COLS)
    ix = {c: cols.index(c) for c in cols}
    has_rssi = "field.rssi" in ix and "field.rssi_fp" in ix
    skipped = Skipped(p)
    out, pos = [], []
    for line, row in rows:
        try:
            if len(row) != len(cols):
                raise BadCell("field.stamp", "", f"expected {len(cols)} fields, got {len(row)}")
            t = (
                int(row[ix["field.stamp"]].strip()) / 1e9
                if row[ix["field.stamp"]].strip().isdigit()
                else finite(row[ix["field.stamp"]], "field.stamp") / 1e9
            )
            xyz = [finite(row[ix[c]], c) for c in ("field.x", "field.y", "field.z")]
            r = finite(row[ix["field.distanceFromTag"]], "field.distanceFromTag")
            rx = num(row[ix["field.rssi"]], "field.rssi") if has_rssi else np.nan
            fp = num(row[ix["field.rssi_fp"]], "field.rssi_fp") if has_rssi else np.nan
        except BadCell as e:
            skipped.add("unparsable row", line, str(e))
            continue
        if r <= 0:
            skipped.add("non-positive range", line)
            continue
        out.append((t, r, fp, rx))
        pos.append(xyz)
    skipped.fail_if_nothing(len(out))
    pos_m = np.asarray(pos)
    truth = np.median(pos_m, axis=0)
    spread = float(np.max(np.abs(pos_m - truth)))
    return np.asarray(out), truth, spread, skipped


def _read_trajectory(p: Path):
    cols, rows = csv_rows(p, ("timestamp", "x", "y", "z"))
    ix = [cols.index(c) for c in ("timestamp", "x", "y", "z")]
    skipped = Skipped(p)
    t, xyz = [], []
    last = -np.inf
    for line, row in rows:
        try:
            if len(row) != len(cols):
                raise BadCell("timestamp", "", f"expected {len(cols)} fields, got {len(row)}")
            ti = finite(row[ix[0]], "timestamp") / 1e9
            v = [finite(row[i], c) for i, c in zip(ix[1:], "xyz", strict=False)]
        except BadCell as e:
            skipped.add("unparsable row", line, str(e))
            continue
        if ti <= last:
            skipped.add("non-increasing time", line)
            continue
        last = ti
        t.append(ti)
        xyz.append(v)
    skipped.fail_if_nothing(len(t))
    if len(t) < 2:
        raise JaxcalError(f"{p}: need at least 2 trajectory rows, got {len(t)}")
    return np.asarray(t), np.asarray(xyz), skipped


def import_hanyang(run_dir: str | os.PathLike, name: str | None = None) -> TrajectoryDataset:
    """Read one Hanyang dynamic run into a trajectory dataset.

    Args:
        run_dir: the run folder with `A<id>.csv` files and `trajectory.csv`.
        name: dataset name; default `hanyang-<LOS|NLOS>-<Trajectory_X>-<Case_N>` from the path.

    Returns:
        `TrajectoryDataset`: A anchors with truth (A, 3), one tag (zero lever arm), RTK poses, ranges
        with `range_los` from the folder name and signal powers.
    """
    d = existing_dir(run_dir)
    files = sorted((f for f in d.iterdir() if _ANCHOR_FILE.match(f.name)), key=lambda f: int(f.name[1:].split(".")[0]))
    if not files:
        raise JaxcalError(f"{d}: no anchor file A<id>.csv")
    pt, ppos, sk_t = _read_trajectory(existing_file(d / "trajectory.csv"))
    anchor_ids, truth, chunks, notes_skip = [], [], [], []
    n_outside = 0
    moved = []
    for a, f in enumerate(files):
        rows, pos, spread, sk = _read_anchor(existing_file(f))
        inside = (rows[:, 0] >= pt[0]) & (rows[:, 0] <= pt[-1])
        n_outside += int((~inside).sum())
        rows = rows[inside]
        anchor_ids.append(f.stem)
        truth.append(pos)
        if spread > 0.01:
            moved.append(f"{f.stem} ({spread:.3f} m)")
        chunks.append(np.column_stack([rows, np.full(len(rows), a)]))
        notes_skip.append(sk.describe())
    allr = np.concatenate(chunks)
    allr = allr[np.argsort(allr[:, 0], kind="stable")]
    if allr.shape[0] == 0:
        raise JaxcalError(f"{d}: no range inside the reference trajectory's time span")
    los = los_label(d)
    los_word = {1: "LOS", 0: "NLOS", -1: "unknown"}[los]
    parts = Path(d).resolve().parts
    default = "hanyang-" + "-".join(parts[-3:]) if len(parts) >= 3 else f"hanyang-{d.name}"
    notes = [
        f"Hanyang outdoor run {'/'.join(parts[-3:])}: {allr.shape[0]} ranges to {len(files)} anchors, "
        f"{pt.size} RTK poses, ranges/los = {los} ({los_word} run folder)",
        f"{n_outside} range(s) outside the trajectory's time span dropped",
        f"anchor position column varies for {', '.join(moved)}: truth = median" if moved else "",
        *notes_skip,
        sk_t.describe(),
    ]
    return TrajectoryDataset(
        name=name or default,
        anchor_ids=tuple(anchor_ids),
        tag_ids=("tag",),
        lever_arm=np.zeros((1, 3)),
        pose_time=pt,
        pose_position=ppos,
        range_time=allr[:, 0],
        range_anchor=allr[:, 4].astype(np.int32),
        range_tag=np.zeros(allr.shape[0], np.int32),
        range=allr[:, 1].astype(np.float32),
        range_los=np.full(allr.shape[0], los, np.int8),
        fp_rssi=allr[:, 2].astype(np.float32),
        rx_rssi=allr[:, 3].astype(np.float32),
        anchor_truth=np.asarray(truth),
        description=join_notes(*notes),
        source=SOURCE,
        license=LICENSE,
    )
