"""Generic long-table importer: `time,from,to,range[,los][,fp_rssi][,rx_rssi]` -> `MeshDataset`.

One row is one range measurement from node `from` to node `to` at `time` [s] in metres. Epochs are the
unique times (sorted); node ids are the `from`/`to` values in order of first appearance (row order,
`from` before `to`). Directed pairs stay separate (i->j and j->i may differ). The per-row `los`
(1, 0, -1 or empty) becomes the per-link `links/los` matrix: a directed link whose rows all agree
gets that value, a link with mixed or no labels gets -1 (unknown).

Skipped and counted (reported in `description`): rows with a non-numeric or missing time or range,
a negative range, `from == to`, a bad `los` value, or the wrong number of fields. A repeated
(time, from, to) keeps the last row and is counted as a duplicate.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from jaxcal.data import MeshDataset
from jaxcal.io.importers._common import BadCell, Skipped, csv_rows, existing_file, finite, join_notes, num

__all__ = ["import_csv"]

REQUIRED = ("time", "from", "to", "range")


def import_csv(path: str | os.PathLike, name: str | None = None) -> MeshDataset:
    """Read a long csv table of ranges into a mesh dataset.

    Args:
        path: csv file with header `time,from,to,range` and optional `los`, `fp_rssi`, `rx_rssi`.
        name: dataset name; default the file stem.

    Returns:
        `MeshDataset` with K = number of unique times, N = number of distinct ids, no truth.
    """
    p = existing_file(path)
    cols, rows = csv_rows(p, REQUIRED)
    ix = {c: cols.index(c) for c in cols if c}
    opt = [c for c in ("los", "fp_rssi", "rx_rssi") if c in ix]
    skipped = Skipped(p)
    recs: dict[tuple[float, str, str], tuple] = {}
    n_dup = 0
    ids: dict[str, int] = {}
    for line, row in rows:
        if len(row) != len(cols):
            skipped.add("wrong field count", line, f"expected {len(cols)} fields, got {len(row)}")
            continue
        try:
            t = finite(row[ix["time"]], "time")
            r = finite(row[ix["range"]], "range")
            a, b = row[ix["from"]].strip(), row[ix["to"]].strip()
            if not a or not b:
                raise BadCell("from" if not a else "to", "", "empty id")
            if r < 0:
                raise BadCell("range", row[ix["range"]], "negative range")
            if a == b:
                raise BadCell("to", b, "same node as 'from'")
            extra = []
            for c in opt:
                v = num(row[ix[c]], c)
                if c == "los":
                    if v != v:
                        v = -1.0
                    if v not in (-1.0, 0.0, 1.0):
                        raise BadCell("los", row[ix[c]], "not 1, 0 or -1")
                extra.append(v)
        except BadCell as e:
            reason = "negative range" if "negative" in str(e) else "self range" if "same node" in str(e) else "bad cell"
            skipped.add(reason, line, str(e))
            continue
        for node in (a, b):
            ids.setdefault(node, len(ids))
        key = (t, a, b)
        n_dup += key in recs
        recs[key] = (r, *extra)
    skipped.fail_if_nothing(len(recs))

    times = np.unique(np.fromiter((k[0] for k in recs), float, len(recs)))
    n, k = len(ids), len(times)
    t_idx = {t: i for i, t in enumerate(times.tolist())}
    rng = np.full((k, n, n), np.nan, np.float32)
    power = {c: np.full((k, n, n), np.nan, np.float32) for c in opt if c != "los"}
    los_seen = np.zeros((n, n, 3), bool)  # labels -1, 0, 1 seen per directed link
    for (t, a, b), vals in recs.items():
        ep, i, j = t_idx[t], ids[a], ids[b]
        rng[ep, i, j] = vals[0]
        for c, v in zip(opt, vals[1:], strict=False):
            if c == "los":
                los_seen[i, j, int(v) + 1] = True
            else:
                power[c][ep, i, j] = v
    los = None
    if "los" in opt:
        los = np.full((n, n), -1, np.int8)
        single = los_seen.sum(axis=2) == 1
        los[single] = np.argmax(los_seen, axis=2)[single] - 1
    notes = [f"imported from {p.name}: {len(recs)} ranges, {k} epochs, {n} nodes"]
    if n_dup:
        notes.append(f"{n_dup} duplicate (time, from, to) row(s): kept the last")
    notes.append(skipped.describe())
    return MeshDataset(
        name=name or Path(p).stem,
        node_ids=tuple(ids),
        time=times,
        range=rng,
        los=los,
        fp_rssi=power.get("fp_rssi"),
        rx_rssi=power.get("rx_rssi"),
        description=join_notes(*notes),
        source=f"generic csv table {p.name}",
    )
