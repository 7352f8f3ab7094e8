"""What kind of jaxcal file a path is, for `info` and `validate`: every file jaxcal writes.

Kinds: the contract's `mesh`, `trajectory`, `result` (HDF5, root attribute `jaxcal_format`); `sweep`
(HDF5 store of `jaxcal sweep`: root attribute `format = "jaxcal-sweep"`, groups runs/ and metrics/,
dataset done); `journal` (`jaxcal record`'s crash journal, OUT.h5.journal); `params` (the JSON of
`jaxcal tune`); `summary` (other JSON that jaxcal writes: demo's summary.json, report's report.json).
"""

from __future__ import annotations

from pathlib import Path

from jaxcal.errors import FormatError

HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


def identify(path: str) -> str:
    """The kind of file at `path` (see the module docstring); a one-line FormatError for anything else."""
    p = Path(path)
    if not p.exists():
        raise FormatError(f"{path}: no such file")
    if p.is_dir():
        raise FormatError(f"{path}: is a folder, not a file")
    with open(p, "rb") as f:
        head = f.read(8)
    if head == HDF5_MAGIC:
        import h5py

        try:
            with h5py.File(p, "r") as f:
                if "jaxcal_format" in f.attrs:
                    from jaxcal.io.hdf5 import read_format

                    return read_format(p)
                fmt = f.attrs.get("format")
                if isinstance(fmt, bytes):
                    fmt = fmt.decode()
                if fmt == "jaxcal-sweep":
                    return "sweep"
        except OSError as e:
            raise FormatError(f"{path}: not a readable HDF5 file ({str(e).splitlines()[0]})") from None
        raise FormatError(f"{path}: missing root attribute 'jaxcal_format' (an HDF5 file, but not a jaxcal file)")
    if p.suffix.lower() in (".h5", ".hdf5", ".hdf"):
        raise FormatError(f"{path}: not a readable HDF5 file (no HDF5 signature)")
    from jaxcal.io.recorder import JOURNAL_MAGIC

    if head.startswith(JOURNAL_MAGIC[:8]):
        return "journal"
    import json

    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, ValueError):
        raise FormatError(f"{path}: not a jaxcal file (neither HDF5, a record journal nor JSON)") from None
    if isinstance(doc, dict) and isinstance(doc.get("params"), dict) and "tuning" in doc:
        return "params"
    if isinstance(doc, dict):
        return "summary"
    raise FormatError(f"{path}: a JSON file, but not one that jaxcal writes (not an object)")


def sweep_summary(path: str) -> dict:
    """A sweep store as a plain dict: method, runs, done, swept parameters, scenarios, metrics' ranges."""
    import numpy as np

    from jaxcal.commands.sweep import read_store

    attrs, runs, metrics, done = read_store(path)
    n = int(done.size)
    for k, v in runs.items():
        if len(v) != n:
            raise FormatError(f"{path}: runs/{k} has {len(v)} entries, done has {n}")
    for k, v in metrics.items():
        if len(v) != n:
            raise FormatError(f"{path}: metrics/{k} has {len(v)} entries, done has {n}")

    def text(v):
        return v.decode() if isinstance(v, bytes) else str(v)

    swept = [s for s in text(attrs.get("swept", "")).split(",") if s]
    out = {
        "format": "sweep",
        "method": text(attrs.get("method", "")),
        "runs": n,
        "done": int(done.sum()),
        "swept": {s: sorted({float(x) for x in runs.get(f"param_{s}", [])}) for s in swept},
        "scenarios": sorted({str(s) for s in runs.get("scenario", [])}),
        "seeds": sorted({int(s) for s in runs.get("seed", [])}),
        "fixed_params": text(attrs.get("fixed_params", "")),
        "metrics": {},
    }
    for k, v in metrics.items():
        ok = np.isfinite(v) & done
        out["metrics"][k] = [float(v[ok].min()), float(v[ok].max())] if ok.any() else None
    return out


def journal_summary(path: str) -> dict:
    """A record journal: its header, frames kept, bytes of a torn tail."""
    from jaxcal.io.recorder import read_journal

    header, records, torn = read_journal(path)
    times = [t for t, _ in records]
    return {
        "format": "journal",
        "header": header,
        "frames": len(records),
        "torn_bytes": int(torn),
        "time_span_s": [min(times), max(times)] if times else None,
    }


def params_summary(path: str) -> dict:
    """A `jaxcal tune` parameter file; its keys are checked against the tuned method's parameters."""
    import json

    from jaxcal.methods import param_defaults
    from jaxcal.params import with_overrides

    doc = json.loads(Path(path).read_text(encoding="utf-8"))
    method = str(doc.get("tuning", {}).get("method", "pgp"))
    try:
        for d in param_defaults(method):
            with_overrides(d, doc["params"])
    except Exception as e:  # noqa: BLE001 - any bad key or value: the file is not valid
        raise FormatError(f"{path}: {' '.join(str(e).split())}") from None
    return {"format": "params", "method": method, "params": doc["params"], "tuning": doc.get("tuning", {})}
