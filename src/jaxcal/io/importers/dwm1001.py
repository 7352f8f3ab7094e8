"""Importer of the dwm1001-autocal recordings (esauortiz/dwm1001_drivers, Sensors 2020, 20(19), 5613).

Layout: a scenario folder holding one `<NODE>_ranging_data.txt` per measuring node, plus the
scenario's `nodes_cfg/<scenario>.yaml`. Each file is a whitespace-separated float matrix
(n_samples, N): row = sample, column = target node in the yaml's order `network0.anchor0..`,
`network1.anchor0..` (by network number, not by the order of the yaml's keys), value = range [m],
-1 = no measurement (and the self column).

Epoch rule: the files carry no timestamps. The nodes took turns ranging every other node, one
ranging round per row, so epoch k is row k of every file (`range[k, i, j]` = file i, row k,
column j) and `epochs/time` is the nominal round index k in seconds (0, 1, 2, ...). Files of
different lengths are padded with NaN. Rounds without a single range (row 0 is usually all -1) are
dropped and counted. i->j and j->i stay separate measurements.

Cleaning: -1 (the logger's "no measurement"), any other negative value, a non-finite value and a
value above `MAX_RANGE_M` (physically absurd for DWM1001 TWR) become NaN; the count of values other
than -1 that were dropped is reported in `description`. A line with the wrong number of columns or a
non-numeric cell is skipped and counted. The diagonal is NaN.

Truth: the yaml's `gt` coordinates; 2-D (x, y) when every z is equal (planar scenarios), else 3-D.

Configurations (from the measurements only, never from the truth): a frame needs a well-connected,
non-degenerate triangle. For each triple, connectivity is the smallest, over its three pairs, share of
epochs with a range in either direction; the triangle is judged by the median measured range of each
pair (smallest interior angle by the law of cosines, >= `MIN_FRAME_ANGLE_DEG`). `conf1` = the best
connected such triple, `conf2` = the worst connected one among triples whose pairs were all measured
at least once (ties broken by the sum of the pair shares, then by index order). The default frame
stays (0, 1, 2).

Source: github.com/esauortiz/dwm1001_drivers @ 21ab15e; no licence stated upstream (local use only).
"""

from __future__ import annotations

import itertools
import math
import os
import warnings
from pathlib import Path

import numpy as np

from jaxcal.data import MeshDataset
from jaxcal.errors import JaxcalError
from jaxcal.io.importers._common import existing_dir, existing_file, join_notes

__all__ = ["import_dwm1001", "read_nodes_cfg", "MAX_RANGE_M", "MIN_FRAME_ANGLE_DEG"]

MAX_RANGE_M = 1000.0
MIN_FRAME_ANGLE_DEG = 20.0
SOURCE = (
    "github.com/esauortiz/dwm1001_drivers @ 21ab15e7205d531ca0f5b14f6e0101087aa5c1e3, "
    "autocalibration_datasets/uart; Ortiz et al., Sensors 2020, 20(19), 5613"
)
LICENSE = "none stated upstream (local use only; do not redistribute)"


def read_nodes_cfg(path: str | os.PathLike) -> tuple[list[str], np.ndarray | None]:
    """Node ids and `gt` positions from a nodes_cfg yaml.

    Args:
        path: the scenario's `nodes_cfg/<scenario>.yaml`.

    Returns:
        (ids, truth): ids in column order (network0.anchor0.., network1.anchor0..); truth (N, 3) [m]
        with NaN rows where a node has no `gt` entry, or None when no node has one.
    """
    import yaml

    p = existing_file(path, "yaml file")
    try:
        cfg = yaml.safe_load(p.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise JaxcalError(f"{p}: not a valid yaml file ({' '.join(str(e).split())[:100]})") from None
    if not isinstance(cfg, dict):
        raise JaxcalError(f"{p}: expected a mapping with networkN entries")
    nets = sorted(
        (k for k in cfg if isinstance(k, str) and k.startswith("network") and k[7:].isdigit()), key=lambda k: int(k[7:])
    )
    if not nets:
        raise JaxcalError(f"{p}: no 'network0', 'network1', ... entries")
    ids, truth = [], []
    for net in nets:
        d = cfg[net]
        if not isinstance(d, dict):
            raise JaxcalError(f"{p}: '{net}' is not a mapping")
        gt = d.get("gt") or {}
        keys = sorted(
            (k for k in d if isinstance(k, str) and k.startswith("anchor") and k.endswith("_id")),
            key=lambda k: int(k[6:-3]) if k[6:-3].isdigit() else 1 << 30,
        )
        for k in keys:
            ids.append(str(d[k]).strip())
            c = gt.get(k[:-3] + "_coordinates")
            try:
                xyz = [float(v) for v in c] if c is not None else [math.nan] * 3
            except (TypeError, ValueError):
                raise JaxcalError(f"{p}: '{net}.gt.{k[:-3]}_coordinates' is not a list of numbers") from None
            if len(xyz) != 3:
                raise JaxcalError(f"{p}: '{net}.gt.{k[:-3]}_coordinates' must have 3 values, got {len(xyz)}")
            truth.append(xyz)
    if len(set(ids)) != len(ids):
        raise JaxcalError(f"{p}: duplicate node id in the networks")
    t = np.asarray(truth, float)
    return ids, (None if np.isnan(t).all() else t)


def _read_matrix(path: Path, n: int) -> tuple[np.ndarray, int]:
    """(rows, n) float matrix of one node's file; bad lines become NaN rows. Returns (matrix, n_bad)."""
    rows, bad = [], 0
    first_bad = None
    with open(path, encoding="utf-8", errors="replace") as f:
        for line_no, line in enumerate(f, 1):
            parts = line.split()
            if not parts:
                continue
            try:
                if len(parts) != n:
                    raise ValueError(f"expected {n} columns, got {len(parts)}")
                rows.append([float(v) for v in parts])
            except ValueError as e:
                bad += 1
                first_bad = first_bad or f"{path}:{line_no}: {e}"
                rows.append([math.nan] * n)
    if bad == len(rows):
        raise JaxcalError(first_bad + " (no usable line in the file)" if first_bad else f"{path}: empty file")
    return np.asarray(rows, float), bad


def _frame_configs(rng: np.ndarray) -> dict[str, tuple[int, int, int]]:
    """conf1 / conf2 from connectivity and measured triangle shape (see the module docstring)."""
    meas = np.isfinite(rng)
    either = meas | meas.transpose(0, 2, 1)
    share = either.mean(axis=0)  # (N, N) share of epochs with a range in either direction
    with warnings.catch_warnings():  # all-NaN pairs (never measured) give NaN medians, as intended
        warnings.simplefilter("ignore", RuntimeWarning)
        both = np.where(meas, rng, np.nan)
        both = np.concatenate([both, both.transpose(0, 2, 1)], axis=0)
        med = np.nanmedian(both, axis=0) if both.size else np.full(share.shape, np.nan)
    cands = []
    for tri in itertools.combinations(range(rng.shape[1]), 3):
        pairs = list(itertools.combinations(tri, 2))
        s = [share[i, j] for i, j in pairs]
        if min(s) <= 0:
            continue
        a, b, c = (med[i, j] for i, j in pairs)
        if not (np.isfinite([a, b, c]).all() and min(a, b, c) > 0):
            continue
        angles = []
        for x, y, z in ((a, b, c), (b, c, a), (c, a, b)):  # angle opposite z
            cos = (x * x + y * y - z * z) / (2 * x * y)
            angles.append(math.degrees(math.acos(min(1.0, max(-1.0, cos)))))
        if min(angles) >= MIN_FRAME_ANGLE_DEG:
            cands.append((min(s), sum(s), tri))
    if not cands:
        return {}
    best = max(cands, key=lambda c: (c[0], c[1], tuple(-i for i in c[2])))
    worst = min(cands, key=lambda c: (c[0], c[1], c[2]))
    out = {"conf1": best[2]}
    if worst[2] != best[2]:
        out["conf2"] = worst[2]
    return out


def import_dwm1001(
    scenario_dir: str | os.PathLike, nodes_cfg: str | os.PathLike, name: str | None = None, force: bool = False
) -> MeshDataset:
    """Read one dwm1001-autocal scenario into a mesh dataset.

    Args:
        scenario_dir: folder with the `<NODE>_ranging_data.txt` files.
        nodes_cfg: the scenario's nodes_cfg yaml (node order and `gt` truth).
        name: dataset name; default `dwm1001-<yaml stem>`.
        force: import even when the folder holds files of nodes that the yaml does not list (their
            ranges are then left out); otherwise that is an error. A yaml node without a file is only
            noted (its row is NaN; the other nodes' ranges to it are kept).

    Returns:
        `MeshDataset` (K rounds, N nodes, truth (N, 2) or (N, 3)), configurations conf1/conf2.
    """
    d = existing_dir(scenario_dir)
    ids, truth = read_nodes_cfg(nodes_cfg)
    n = len(ids)
    mats: list[np.ndarray | None] = []
    missing: list[str] = []
    bad_lines = 0
    for node in ids:
        f = d / f"{node}_ranging_data.txt"
        if not f.is_file():
            missing.append(node)
            mats.append(None)
            continue
        existing_file(f)
        m, bad = _read_matrix(f, n)
        bad_lines += bad
        mats.append(m)
    if len(missing) == n:
        raise JaxcalError(f"{d}: no '<NODE>_ranging_data.txt' file for any node of {Path(nodes_cfg).name}")
    suffix = "_ranging_data.txt"
    extra = sorted(f.name[: -len(suffix)] for f in d.glob(f"*{suffix}") if f.name[: -len(suffix)] not in ids)
    if extra and not force:
        lacking = f"; layout node(s) {', '.join(missing)} have no file" if missing else ""
        raise JaxcalError(
            f"{d}: node ids do not match {Path(nodes_cfg).name}: files for node(s) {', '.join(extra)} that the "
            f"layout does not list{lacking} (--force imports anyway, without them)"
        )
    k = max(m.shape[0] for m in mats if m is not None)
    raw = np.full((k, n, n), np.nan)
    for i, mat in enumerate(mats):
        if mat is not None:
            raw[: mat.shape[0], i, :] = mat
    raw[:, np.arange(n), np.arange(n)] = np.nan
    no_meas = raw == -1.0
    absurd = ~no_meas & ~np.isnan(raw) & ((raw < 0) | (raw > MAX_RANGE_M) | ~np.isfinite(raw))
    rng = np.where(no_meas | absurd | ~np.isfinite(raw), np.nan, raw)
    keep = np.isfinite(rng).any(axis=(1, 2))
    time = np.arange(k, dtype=float)[keep]
    rng = rng[keep]
    if rng.shape[0] == 0:
        raise JaxcalError(f"{d}: no valid range in any file")

    if truth is not None and np.nanmax(truth[:, 2]) - np.nanmin(truth[:, 2]) == 0:
        truth = truth[:, :2]
    configs = _frame_configs(rng)
    notes = [
        f"dwm1001-autocal scenario {Path(nodes_cfg).stem} ({d.name}): {n} nodes, {rng.shape[0]} ranging rounds "
        f"(epoch = row of every node's file, time = round index), {int(np.isfinite(rng).sum())} ranges",
        f"{int(absurd.sum())} negative or absurd value(s) (other than -1) set to NaN",
        f"{int((~keep).sum())} round(s) without any range dropped",
    ]
    if bad_lines:
        notes.append(f"{bad_lines} malformed line(s) skipped")
    if missing:
        notes.append(f"no file for node(s) {', '.join(missing)} (their rows are NaN)")
    if extra:
        notes.append(f"file(s) of node(s) {', '.join(extra)} not in the layout ignored")
    if configs:
        notes.append(
            "configs: "
            + ", ".join(f"{c}={v}" for c, v in configs.items())
            + " (conf1 best connected, conf2 worst connected non-degenerate triangle)"
        )
    return MeshDataset(
        name=name or f"dwm1001-{Path(nodes_cfg).stem}",
        node_ids=tuple(ids),
        time=time,
        range=rng.astype(np.float32),
        truth=truth,
        configs=tuple(configs.items()),
        description=join_notes(*notes),
        source=SOURCE,
        license=LICENSE,
    )
