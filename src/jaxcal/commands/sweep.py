"""`jaxcal sweep SPEC.toml -o SWEEP.h5 [--coordinator HOST:PORT --num-processes P --process-id I]`:
a parameter x scenario x seed grid of the grid filter, sharded over devices and processes,
resumable; runs one by one on the fast path on CPU, vmapped on accelerators (`--execution`).

The output is rewritten whole after every batch (temporary file + `os.replace`), so a killed sweep
leaves either the previous or the new complete file, never a torn one; on restart the runs whose
`done` flag is set are skipped. Progress: a bar (runs done, runs/s, ETA) on a terminal, else one
line per batch on stderr (log files of cluster jobs); `--quiet` neither.
"""

from __future__ import annotations

FORMAT = "jaxcal-sweep"


def add_arguments(p) -> None:
    p.add_argument("spec", help="sweep specification (TOML, see docs/cluster.md)")
    p.add_argument("-o", "--output", required=True, metavar="SWEEP.h5", help="results (created or resumed)")
    p.add_argument("--restart", action="store_true", help="discard an existing output instead of resuming")
    p.add_argument(
        "--batch-size",
        type=int,
        default=None,
        help="runs per device in one batch (overrides the spec)",
    )
    p.add_argument(
        "--execution",
        choices=("auto", "sequential", "vmap"),
        default=None,
        help="runs one by one on the fast path (CPU default) or vmapped batches (accelerator "
        "default); overrides the spec",
    )
    p.add_argument(
        "--coordinator",
        default=None,
        metavar="HOST:PORT",
        help="jax.distributed coordinator address (multi-process sweep)",
    )
    p.add_argument("--num-processes", type=int, default=None, help="number of processes (with --coordinator)")
    p.add_argument(
        "--process-id",
        type=int,
        default=None,
        help="this process's id, 0 .. P-1 (with --coordinator)",
    )
    p.add_argument(
        "--throttle",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="pause after each batch (demonstrating interruption and resumption)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar or lines, no summary line")
    p.add_argument("--json", action="store_true", help="print a JSON summary")


def _spec_text(path: str) -> tuple[str, dict]:
    import tomllib
    from pathlib import Path

    from jaxcal.errors import JaxcalError

    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise JaxcalError(f"{p}: no such file") from None
    except UnicodeDecodeError:
        raise JaxcalError(f"{p}: not a text file") from None
    try:
        return text, tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise JaxcalError(f"{p}: not valid TOML ({e})") from None


def _datasets(spec, pl, spec_dir):
    """One (dataset, config) per plan dataset; files relative to the spec's folder."""
    from pathlib import Path

    from jaxcal.commands._common import load, resolve_config
    from jaxcal.sweep import simulate_or_raise

    cache, out = {}, []
    for si, seed in pl.datasets:
        sc = spec.scenarios[si]
        if sc.file is not None:
            path = Path(sc.file)
            path = path if path.is_absolute() else Path(spec_dir) / path
            if str(path) not in cache:
                cache[str(path)] = load(str(path), ("mesh",))
            out.append(resolve_config(cache[str(path)], sc.config))  # a name or three node ids
        else:
            out.append(resolve_config(simulate_or_raise(sc, seed), sc.config))
    return out


def read_store(path: str):
    """(attrs, columns dict, metrics dict, done) of a sweep file."""
    import h5py
    import numpy as np

    from jaxcal.errors import FormatError

    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != FORMAT:
                raise FormatError(f"{path}: not a jaxcal sweep file")
            attrs = dict(f.attrs)
            runs = {k: f["runs"][k][()] for k in f["runs"]}
            metrics = {k: f["metrics"][k][()] for k in f["metrics"]}
            done = np.asarray(f["done"][()], bool)
    except OSError as e:
        raise FormatError(f"{path}: not a readable HDF5 file ({e})") from None
    runs = {k: (v.astype(str) if v.dtype.kind in "SO" else v) for k, v in runs.items()}
    return attrs, runs, metrics, done


def _write_store(path, attrs, runs, metrics, done) -> None:
    """Whole file to a temporary name, then `os.replace` (`jaxcal.io.atomic`)."""
    import h5py

    from jaxcal.io.atomic import atomic_path

    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        for k, v in attrs.items():
            f.attrs[k] = v
        g = f.create_group("runs")
        for k, v in runs.items():
            g.create_dataset(k, data=v.astype("S") if v.dtype.kind == "U" else v)
        m = f.create_group("metrics")
        for k, v in metrics.items():
            m.create_dataset(k, data=v)
        f.create_dataset("done", data=done)


def run(args) -> int:
    import hashlib
    import os
    import sys
    import time
    from pathlib import Path

    from jaxcal.errors import JaxcalError

    dist = (args.coordinator, args.num_processes, args.process_id)
    if any(x is not None for x in dist):
        if any(x is None for x in dist):
            raise JaxcalError("--coordinator, --num-processes and --process-id go together")
        if not 0 <= args.process_id < args.num_processes:
            raise JaxcalError(f"--process-id must be in [0, {args.num_processes})")
    if args.batch_size is not None and args.batch_size < 1:
        raise JaxcalError("--batch-size must be >= 1")
    text, doc = _spec_text(args.spec)
    from jaxcal.commands._common import check_output_path

    checked = check_output_path(args.output, [args.spec])
    if args.batch_size is not None:
        doc["batch_size"] = args.batch_size
    if args.execution is not None:
        doc["execution"] = args.execution
    import jax

    if args.coordinator:
        jax.distributed.initialize(
            coordinator_address=args.coordinator,
            num_processes=args.num_processes,
            process_id=args.process_id,
        )
    import numpy as np

    from jaxcal import sweep as S
    from jaxcal.commands._common import print_json

    spec = S.parse_spec(doc)
    pl = S.plan(spec)
    writer = jax.process_index() == 0
    # batch size changes neither runs nor results: it is not part of the identity of a sweep
    identity = repr((spec.method, spec.epochs, spec.params, spec.grid, spec.scenarios))
    ident = hashlib.sha256(identity.encode()).hexdigest()
    runs = {
        "scenario": np.asarray([spec.scenarios[pl.datasets[d][0]].label for d in pl.dataset_of]),
        "config": np.asarray([spec.scenarios[pl.datasets[d][0]].config or "" for d in pl.dataset_of]),
        "seed": np.asarray([pl.datasets[d][1] for d in pl.dataset_of], np.int64),
        **{f"param_{k}": v for k, v in pl.values.items()},
    }
    metrics = {k: np.full(pl.n_runs, np.nan) for k in S.METRICS}
    done = np.zeros(pl.n_runs, bool)
    out = Path(args.output)
    if writer and out.exists() and not args.restart:
        attrs, _, old_metrics, old_done = read_store(str(out))
        if attrs.get("spec_id") != ident or old_done.shape != done.shape:
            raise JaxcalError(f"{out}: written by a different sweep spec (use --restart or another output)")
        done, metrics = old_done, {k: old_metrics.get(k, metrics[k]) for k in S.METRICS}
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        done = np.array(multihost_utils.broadcast_one_to_all(done), dtype=bool)  # a writable copy
    attrs = {
        "format": FORMAT,
        "spec_id": ident,
        "spec_toml": text,
        "method": spec.method,
        "epochs": -1 if spec.epochs is None else spec.epochs,
        "fixed_params": repr(dict(spec.params)),
        "swept": ",".join(pl.values),
    }
    resumed = int(done.sum())
    todo = pl.n_runs - resumed
    log = (lambda msg: sys.stderr.write(msg + "\n")) if writer and not args.quiet else (lambda msg: None)
    execution = S.resolve_execution(spec.execution)
    log(
        f"sweep: {pl.n_runs} runs on {jax.device_count()} device(s) in "
        f"{jax.process_count()} process(es), {execution} execution"
        + (f", resuming with {resumed} done" if resumed else "")
    )
    from jaxcal.progress import progress_bar, wanted

    # a bar on a terminal; otherwise (log files, pipes) one line per batch
    bar_on = writer and wanted(not args.quiet)
    if bar_on:
        log = lambda msg: None  # noqa: E731
    computed, t0 = 0, time.perf_counter()
    if todo:
        groups, group_of = S.build_groups(_datasets(spec, pl, os.path.dirname(os.path.abspath(args.spec))), spec)
        if writer:
            _write_store(out, attrs, runs, metrics, done)
        with progress_bar(todo, "sweep", "run", enabled=bar_on) as bar:
            # per run with one process; with several, per batch (a callback sees local runs only)
            per_run = jax.process_count() == 1
            batches = S.execute(spec, pl, groups, group_of, done, progress=bar.update if per_run else None)
            for idx, vals in batches:
                for k, v in vals.items():
                    metrics[k][idx] = v
                done[idx] = True
                computed += idx.size
                if not per_run:
                    bar.update(int(idx.size))
                if writer:
                    _write_store(out, attrs, runs, metrics, done)
                el = time.perf_counter() - t0
                rate = computed / el if el > 0 else float("nan")
                eta = (todo - computed) / rate if rate > 0 else float("nan")
                log(
                    f"sweep: {int(done.sum())}/{pl.n_runs} runs ({100 * done.mean():.0f} %), "
                    f"{rate:.2f} runs/s, "
                    f"ETA {eta:.0f} s"
                )
                if args.throttle > 0:
                    time.sleep(args.throttle)
    elif writer:
        _write_store(out, attrs, runs, metrics, done)
    el = time.perf_counter() - t0
    if writer:
        summary = {
            "output": str(out),
            "runs": pl.n_runs,
            "computed": computed,
            "resumed": resumed,
            "seconds": el,
            "devices": jax.device_count(),
            "processes": jax.process_count(),
            "overwrote": bool(args.restart and checked.existed),
        }
        if args.json:
            print_json(summary)
        elif not args.quiet:
            print(
                f"sweep: {computed} runs computed ({resumed} already done) in {el:.1f} s -> {out}"
                + (f" (overwrote {out})" if summary["overwrote"] else "")
            )
    return 0
