"""Mesh calibration cost against network size at constant density (issue #26): the N-curve.

For each N: `jaxcal simulate mesh --scenario network --nodes N` (random site at constant density,
pairs within `--range-limit` measured, walls, 200 epochs; `jaxcal.sim.network`), then each jaxcal
method as a whole `jaxcal calibrate` process (start-up and compilation included, as a user runs it),
and the SciPy peer a user would write (robust least squares, soft_l1, on the per-pair medians, best
cost of `--peer-starts` random starts) in this process. Per run: wall time, CPU time (user + system; on
a shared machine the steadier measure), the load average, the process's peak resident memory
(`os.wait4` rusage of the child; the peer: this process's peak), aligned RMSE of the final positions
against the truth (best rigid motion with reflection, placed nodes only) and the number of nodes placed.
A run past `--timeout` is stopped and marked so.

Usage:
    python benchmarks/large_networks.py --nodes 10,20,40,100 --methods batch,pgp,pgp+batch,scipy \
        [--seed 0] [--timeout 1800] [--out bench-out/large]
Prints one JSON line per run, then a Markdown table; writes table.md, runs.jsonl and nodes.png
(whole-process time and aligned RMSE against N) into --out. The SciPy peer runs up to
`--peer-max-nodes` (its random starts take tens of minutes at N = 300). `--replot RUNS.jsonl ...`
redraws the figure and the table from earlier runs (e.g. two invocations with different --nodes).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# LAPACK on one thread for the SciPy peer in this process too, as `jaxcal` sets it for itself (jaxcal.cli):
# OpenBLAS's worker threads spin on a busy machine and would charge the peer for it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from peers import aligned_rmse, median_matrix  # noqa: E402

JAXCAL_METHODS = ("batch", "pgp", "pgp+batch", "cf", "parametric")


def run_process(cmd: list[str], timeout: float) -> tuple[int | None, float, float, float]:
    """(exit code or None on time-out, wall [s], peak RSS [MiB], CPU time (user + system) [s]) of one
    child process. On a shared machine the CPU time is the steadier measure of the work done."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = t0 + timeout
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            wall = time.perf_counter() - t0
            proc.returncode = os.waitstatus_to_exitcode(status)
            return proc.returncode, wall, usage.ru_maxrss / 1024.0, usage.ru_utime + usage.ru_stime
        if time.perf_counter() > deadline:
            os.killpg(proc.pid, signal.SIGKILL)
            _, status, usage = os.wait4(proc.pid, 0)
            return None, time.perf_counter() - t0, usage.ru_maxrss / 1024.0, usage.ru_utime + usage.ru_stime
        time.sleep(0.05)


def peer_scipy_starts(range_m: np.ndarray, starts: int, seed: int) -> np.ndarray:
    """SciPy least_squares(soft_l1, f_scale 0.2) on the medians; lowest cost of random starts."""
    from scipy.optimize import least_squares

    med = median_matrix(range_m)
    iu, ju = np.triu_indices(med.shape[0], k=1)
    ok = np.isfinite(med[iu, ju])
    i, j, z = iu[ok], ju[ok], med[iu, ju][ok]
    span = float(np.nanmax(z))
    rng = np.random.default_rng(seed)
    best, best_cost = None, np.inf

    def fun(theta):
        x = theta.reshape(-1, 2)
        return np.linalg.norm(x[i] - x[j], axis=1) - z

    for _ in range(starts):
        sol = least_squares(fun, rng.uniform(0, span, (med.shape[0], 2)).ravel(), loss="soft_l1", f_scale=0.2)
        if sol.cost < best_cost:
            best, best_cost = sol.x.reshape(-1, 2), sol.cost
    return best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", default="10,20,40,100")
    ap.add_argument("--methods", default="batch,pgp,pgp+batch,scipy")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--epochs", type=int, default=200)
    ap.add_argument("--timeout", type=float, default=1800.0, help="per run [s]")
    ap.add_argument("--peer-starts", type=int, default=20)
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="METHOD:KEY=VALUE",
        help="extra --set for one method, e.g. batch:estimate=map",
    )
    ap.add_argument("--peer-max-nodes", type=int, default=100, help="no SciPy peer above this N")
    ap.add_argument("--replot", nargs="*", default=None, metavar="RUNS.jsonl", help="redraw from earlier runs")
    ap.add_argument("--out", default="bench-out/large")
    a = ap.parse_args(argv)
    if a.replot is not None:
        rows = [json.loads(x) for f in a.replot for x in Path(f).read_text().splitlines() if x.strip()]
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        return _write(rows, list(dict.fromkeys(r["method"] for r in rows)), out, a.timeout)
    try:
        sizes = [int(s) for s in a.nodes.split(",") if s]
    except ValueError:
        print(f"large_networks: --nodes must be integers, got {a.nodes!r}", file=sys.stderr)
        return 2
    methods = [m for m in a.methods.split(",") if m]
    bad = [m for m in methods if m not in JAXCAL_METHODS + ("scipy",)]
    if bad or not sizes or min(sizes) < 4:
        print(f"large_networks: bad --methods {bad} or --nodes {a.nodes!r}", file=sys.stderr)
        return 2
    extra: dict[str, list[str]] = {}
    for s in a.set:
        m, _, kv = s.partition(":")
        if m not in JAXCAL_METHODS or "=" not in kv:
            print(f"large_networks: bad --set {s!r} (METHOD:KEY=VALUE)", file=sys.stderr)
            return 2
        extra.setdefault(m, []).extend(["--set", kv])
    out = Path(a.out)
    try:  # before any run: a bad output folder must not cost the whole curve
        out.mkdir(parents=True, exist_ok=True)
        (out / ".write-test").touch()
        (out / ".write-test").unlink()
    except OSError as e:
        print(f"large_networks: cannot write in --out {a.out}: {e.strerror}", file=sys.stderr)
        return 2
    from jaxcal.io import hdf5

    rows = []
    env = dict(os.environ, JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", "cpu"))
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            net = Path(tmp) / f"net{n}.h5"
            subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "jaxcal.cli",
                    "simulate",
                    "mesh",
                    "--scenario",
                    "network",
                    "--nodes",
                    str(n),
                    "--epochs",
                    str(a.epochs),
                    "--seed",
                    str(a.seed),
                    "-o",
                    str(net),
                    "--quiet",
                ],
                check=True,
                env=env,
            )
            ds = hdf5.read(net)
            truth = np.asarray(ds.truth)[:, :2]
            pairs = int(np.isfinite(ds.range).any(axis=0).sum() // 2)
            for m in methods:
                if m == "scipy" and n > a.peer_max_nodes:
                    print(f"large_networks: no SciPy peer at N = {n} (--peer-max-nodes {a.peer_max_nodes})", flush=True)
                    continue
                row = {"nodes": n, "pairs": pairs, "method": m, "load": round(os.getloadavg()[0], 1)}
                if m == "scipy":
                    t0, c0 = time.perf_counter(), time.process_time()
                    est = peer_scipy_starts(np.asarray(ds.range), a.peer_starts, a.seed)
                    row.update(
                        seconds=time.perf_counter() - t0,
                        cpu_s=time.process_time() - c0,
                        rc=0,
                        peak_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                    )
                else:
                    res_path = Path(tmp) / f"res{n}_{m.replace('+', '_')}.h5"
                    cmd = [
                        sys.executable,
                        "-m",
                        "jaxcal.cli",
                        "calibrate",
                        str(net),
                        "--method",
                        m,
                        "--config",
                        "conf1",
                        "-o",
                        str(res_path),
                        "--quiet",
                        *extra.get(m, []),
                    ]
                    rc, wall, peak, cpu = run_process(cmd, a.timeout)
                    row.update(seconds=wall, cpu_s=cpu, rc=rc, peak_mib=peak)
                    est = np.asarray(hdf5.read(res_path).position)[:, :2] if rc == 0 else None
                if est is not None:
                    row.update(rmse_m=aligned_rmse(est, truth), placed=int(np.isfinite(est).all(axis=1).sum()))
                print(json.dumps(row), flush=True)
                rows.append(row)
    (out / "runs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return _write(rows, methods, out, a.timeout)


def _write(rows: list[dict], methods: list[str], out: Path, timeout: float) -> int:
    """table.md and nodes.png of the runs (also printed)."""
    lines = [
        "| N | pairs | method | time [s] | CPU time [s] | load | peak memory [MiB] | aligned RMSE [m] | placed |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        t = (
            f"{r['seconds']:.1f}"
            if r["rc"] == 0
            else (f"> {timeout:.0f} (stopped)" if r["rc"] is None else f"failed ({r['rc']})")
        )
        rm = f"{r['rmse_m']:.3f}" if "rmse_m" in r else ""
        lines.append(
            f"| {r['nodes']} | {r['pairs']} | {r['method']} | {t} | {r['cpu_s']:.0f} | {r['load']} |"
            f" {r['peak_mib']:.0f} | {rm} |"
            f" {r.get('placed', '')}/{r['nodes']} |"
        )
    table = "\n".join(lines)
    (out / "table.md").write_text(table + "\n")
    print(table)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, (ax, bx) = plt.subplots(1, 2, figsize=(9, 3.5))
        for m in methods:
            ok = sorted(
                (r["nodes"], r["seconds"], r.get("rmse_m", np.nan)) for r in rows if r["method"] == m and r["rc"] == 0
            )
            if ok:
                n_, t_, e_ = zip(*ok, strict=True)
                ax.loglog(n_, t_, "o-", label=m)
                bx.semilogx(n_, e_, "o-", label=m)
        ax.set_xlabel("nodes N (constant density)")
        ax.set_ylabel("whole-process wall time [s]")
        bx.set_xlabel("nodes N (constant density)")
        bx.set_ylabel("aligned RMSE [m]")
        bx.set_yscale("log")
        for x in (ax, bx):
            x.grid(True, which="both", alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "nodes.png", dpi=120)
    except ImportError:
        pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
