"""Importer of the CUHK-SZ planar dynamic dataset (LIAS-CUHKSZ, MIT) -> `TrajectoryDataset`.

Input: `UWB_dynamic_exp_*.csv` (no header; col 0 wall-clock time `YYYY-MM-DD H:MM:SS.fff`, cols 1..24
ranges [m] in the order a0-t0, a0-t1, a0-t2, a1-t0, ..., a7-t2; ~100 Hz) and
`motion_capture_dynamic_exp_*.csv` (header `time,x,y,z,rotation,,,`; rigid-body centroid [m] and a
4-component quaternion; ~120 Hz). The anchor and tag coordinates below are the constants of the
dataset's `Planar_Dataset/Dynamic/README.md` (`ANCHORS`, `LEVER_ARMS`).

Times are the wall-clock strings read as if UTC, in Unix seconds, for both files. The logger and
mocap clocks are offset; the file keeps the raw times (the trajectory methods estimate the offset).
On the `mid` run a 1-D search over t_mocap = t_uwb + offset gives offset = -0.13 s when minimising
the median over (anchor, tag) pairs of |e - median_pair(e)| (the bias-free spread; e = range - true
distance; 0.047 m there, 0.047 m at offset 0) and -0.35 s when minimising the median |e| itself
(that criterion is flat because the +0.17 m ranging bias dominates it: median |e| 0.169 m at -0.35 s,
0.171 m at -0.13 s, 0.172 m at 0). Either way the offset is a fraction of a second.

Quaternion order, decided from the data (`mid` run, offset searched for each reading, bias-free
spread as above; lower is better):

    reading of columns 5..8                        body z in world   spread [m]
    README (qw, qx, qy, qz), raw                    -1 (flipped)     0.190
    scalar last (qx, qy, qz, qw), raw               tilted            0.092
    identity (orientation ignored)                  +1                0.125
    README order, then x 180 deg (used)             +1                0.047
    README order, then z 180 deg                    -1                0.084

The first and fourth components stay near zero throughout, so in the README order the quaternion is
a 180 degree turn about a horizontal axis: the mocap rigid body was defined upside down (z down)
relative to the tag frame of the README's lever arms. The reading that fits best by a factor of
two is the README's order composed with a 180 degree rotation about the body x axis, which is also
the only one that keeps the body z axis vertical (planar trolley). The importer therefore stores
`poses/orientation` = q_mocap (qw, qx, qy, qz) * q_x(180 deg) in (x, y, z, w) order, i.e.
(qw, qz, -qy, -qx): a pure yaw, with the README's lever arms unchanged. Residuals with this
reading (offset -0.13 s, poses interpolated at range times): median e = +0.171 m, mean e = +0.179 m,
bias-free spread 0.047 m
(the raw ranges carry a bias; the upstream repository provides a bias/slope calibration not applied here).

Skipped and counted (in `description`): UWB cells that are empty (missing), non-positive ranges
(logger failures), unparsable rows; mocap rows that are unparsable or whose time does not increase
(duplicate timestamps: the first sample is kept).

Source: github.com/LIAS-CUHKSZ/Efficient-Pose-Estimation-via-UWB-measurements @ cabd392. Licence: MIT
(Copyright (c) 2023 Haodong JIANG).
"""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path

import numpy as np

from jaxcal.data import TrajectoryDataset
from jaxcal.errors import JaxcalError
from jaxcal.io.importers._common import BadCell, Skipped, csv_rows, existing_file, finite, join_notes, num

__all__ = [
    "import_cuhksz",
    "ANCHORS",
    "LEVER_ARMS",
    "ANCHOR_IDS",
    "TAG_IDS",
    "mocap_to_body_quaternion",
    "parse_wallclock",
]

# Planar_Dataset/Dynamic/README.md: anchors in the global (mocap) frame [m]
ANCHORS = np.array(
    [
        [-3.4203, 3.0053, 1.0442],
        [0.0016, 3.0110, 1.0446],
        [3.6056, 2.9795, 1.0463],
        [3.6011, -0.0008, 1.0422],
        [3.5674, -3.0087, 1.0443],
        [-0.0072, -2.9652, 1.0444],
        [-3.4673, -2.9587, 1.0445],
        [-3.4858, -0.0098, 1.0457],
    ]
)
# Planar_Dataset/Dynamic/README.md: tags in the local (trolley) frame [m]
LEVER_ARMS = np.array(
    [
        [-0.0689, -0.1423, 0.0011],
        [-0.0750, 0.1402, 0.0016],
        [0.2034, 0.1451, -0.0008],
    ]
)
ANCHOR_IDS = tuple(f"a{i}" for i in range(8))
TAG_IDS = tuple(f"t{i}" for i in range(3))
SOURCE = (
    "LIAS-CUHKSZ planar dataset (github.com/LIAS-CUHKSZ/Efficient-Pose-Estimation-via-UWB-measurements "
    "@ cabd39232cb855d3c1160ed16692034f4d41a092, Planar_Dataset/Dynamic)"
)
LICENSE = "MIT (Copyright (c) 2023 Haodong JIANG)"

_DAY0 = _dt.date(1970, 1, 1)
_day_cache: dict[str, float] = {}


def parse_wallclock(s: str) -> float:
    """`YYYY-MM-DD H:MM:SS.fff` (hour may have one digit) -> Unix seconds, read as UTC."""
    date, _, clock = s.strip().partition(" ")
    day = _day_cache.get(date)
    if day is None:
        try:
            day = (_dt.date.fromisoformat(date) - _DAY0).days * 86400.0
        except ValueError:
            raise BadCell("time", s, "not a date-time") from None
        _day_cache[date] = day
    parts = clock.split(":")
    try:
        h, m, sec = int(parts[0]), int(parts[1]), float(parts[2])
    except (ValueError, IndexError):
        raise BadCell("time", s, "not a date-time") from None
    if len(parts) != 3 or not (0 <= h < 24 and 0 <= m < 60 and 0 <= sec < 61):
        raise BadCell("time", s, "not a date-time")
    return day + h * 3600.0 + m * 60.0 + sec


def mocap_to_body_quaternion(q_wxyz: np.ndarray) -> np.ndarray:
    """Body orientation (x, y, z, w) from the mocap's (qw, qx, qy, qz): q * q_x(180 deg).

    Args:
        q_wxyz: (P, 4) mocap quaternions in the README's order.

    Returns:
        (P, 4) unit quaternions, scalar last, of the frame in which the README's lever arms hold.
    """
    w, x, y, z = np.asarray(q_wxyz, float).T
    q = np.stack([w, z, -y, -x], axis=1)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _read_uwb(p: Path):
    _, rows = csv_rows(p, (), header=False)
    skipped = Skipped(p)
    times, ranges = [], []
    n_missing = n_nonpos = 0
    for line, row in rows:
        try:
            if len(row) != 25:
                raise BadCell("0", "", f"expected 25 fields (time + 24 ranges), got {len(row)}")
            t = parse_wallclock(row[0])
            vals = [num(v, str(c)) for c, v in enumerate(row[1:], 1)]
        except BadCell as e:
            skipped.add("unparsable row", line, str(e))
            continue
        for c, v in enumerate(vals):
            if v != v:
                n_missing += 1
            elif v <= 0:
                n_nonpos += 1
            else:
                a, tg = divmod(c, 3)
                times.append(t)
                ranges.append((a, tg, v))
    skipped.fail_if_nothing(len(ranges))
    return np.asarray(times), np.asarray(ranges), n_missing, n_nonpos, skipped


def _read_mocap(p: Path):
    cols, rows = csv_rows(p, ("time", "x", "y", "z"))
    if len(cols) != 8:
        raise JaxcalError(f"{p}:1: expected 8 columns (time, x, y, z, 4 quaternion components), got {len(cols)}")
    skipped = Skipped(p)
    t, pos, quat = [], [], []
    last = -np.inf
    for line, row in rows:
        try:
            if len(row) != 8:
                raise BadCell("time", "", f"expected 8 fields, got {len(row)}")
            ti = parse_wallclock(row[0])
            xyz = [finite(v, c) for v, c in zip(row[1:4], "xyz", strict=False)]
            q = [finite(v, f"q{k}") for k, v in enumerate(row[4:8])]
            if abs(np.linalg.norm(q) - 1.0) > 1e-2:
                raise BadCell("q0", ",".join(row[4:8]), "not a unit quaternion")
        except BadCell as e:
            skipped.add("unparsable row", line, str(e))
            continue
        if ti <= last:
            skipped.add("non-increasing time", line)
            continue
        last = ti
        t.append(ti)
        pos.append(xyz)
        quat.append(q)
    skipped.fail_if_nothing(len(t))
    return np.asarray(t), np.asarray(pos), np.asarray(quat), skipped


def import_cuhksz(
    uwb_csv: str | os.PathLike, mocap_csv: str | os.PathLike, name: str | None = None
) -> TrajectoryDataset:
    """Read one CUHK-SZ dynamic run into a trajectory dataset.

    Args:
        uwb_csv: `UWB_dynamic_exp_*.csv` (24 ranges per row).
        mocap_csv: `motion_capture_dynamic_exp_*.csv` of the same run.
        name: dataset name; default derived from the UWB file name (e.g. "cuhksz-mid").

    Returns:
        `TrajectoryDataset` with 8 anchors (README truth), 3 tags (README lever arms), mocap poses with
        body orientation (see the module docstring), ranges on the raw logger clock.
    """
    pu, pm = existing_file(uwb_csv), existing_file(mocap_csv)
    rt, rr, n_missing, n_nonpos, sk_u = _read_uwb(pu)
    order = np.argsort(rt, kind="stable")
    rt, rr = rt[order], rr[order]
    mt, mpos, mq, sk_m = _read_mocap(pm)
    if mt.size < 2:
        raise JaxcalError(f"{pm}: need at least 2 motion-capture samples, got {mt.size}")
    run = Path(pu).stem.rsplit("_", 1)[-1]
    notes = [
        f"CUHK-SZ planar run {Path(pu).stem}: {rr.shape[0]} ranges (8 anchors x 3 tags), {mt.size} mocap poses",
        "orientation = mocap (qw,qx,qy,qz) * x-180deg (decided from the data; see jaxcal.io.importers.cuhksz)",
        "range times on the raw logger clock (offset to mocap not applied; about -0.13 s on run mid)",
        f"{n_missing} empty range cell(s), {n_nonpos} non-positive range(s) dropped",
        sk_u.describe(),
        sk_m.describe(),
    ]
    return TrajectoryDataset(
        name=name or f"cuhksz-{run}",
        anchor_ids=ANCHOR_IDS,
        tag_ids=TAG_IDS,
        lever_arm=LEVER_ARMS,
        pose_time=mt,
        pose_position=mpos,
        pose_orientation=mocap_to_body_quaternion(mq),
        range_time=rt,
        range_anchor=rr[:, 0].astype(np.int32),
        range_tag=rr[:, 1].astype(np.int32),
        range=rr[:, 2].astype(np.float32),
        anchor_truth=ANCHORS,
        description=join_notes(*notes),
        source=SOURCE,
        license=LICENSE,
    )
