"""Sweeps: metrics equal single runs + evaluate, no recompilation, spec errors, kill/resume,
4 virtual devices and 2 processes equal one device."""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import time

import equinox as eqx
import numpy as np
import pytest

from conftest import ROOT, assert_one_line_error, run_cli
from jaxcal import sweep as S
from jaxcal.errors import JaxcalError
from jaxcal.mesh.pgp import run_pgp
from jaxcal.metrics import evaluate_mesh
from jaxcal.sim.mesh import simulate

FIXED = dict(cell_m=2.0, max_hyp=4, top_k=8, min_refs=2, likelihood="dense")
SPEC = """
method = "pgp"
epochs = 12
batch_size = 2
[params]
cell_m = 2.0
max_hyp = 4
top_k = 8
min_refs = 2
likelihood = "dense"
[grid]
sigma_r = [0.3, 1.0, 2.0]
tau = [0.5, 0.9]
[[scenarios]]
simulate = "small"
config = "conf1"
seeds = [0, 1]
"""
N_RUNS = 12


@pytest.mark.parametrize(
    "extra, grid",
    [
        ({}, {"sigma_r": [0.4, 1.5], "tau": [0.6, 0.95]}),
        # the NLOS mixture kernel's parameters are swept like sigma_r
        ({"range_model": "mixture"}, {"nlos_weight": [0.1, 0.4], "nlos_mean_m": [0.5, 2.0]}),
    ],
)
def test_metrics_equal_single_runs_and_evaluate(extra, grid, caplog):
    doc = {
        "epochs": 12,
        "batch_size": 4,
        "params": {**FIXED, **extra},
        "grid": grid,
        "scenarios": [{"simulate": "small", "config": "conf1", "seeds": [3]}],
    }
    spec = S.parse_spec(doc)
    pl = S.plan(spec)
    ds = simulate("small", 3)
    with caplog.at_level(logging.WARNING, logger="jaxcal"):
        groups, group_of = S.build_groups([(ds, "conf1")], spec)
    assert len([m for m in caplog.messages if "mirror check" in m]) == 1  # the sweep says what it leaves out
    by = {}
    for execution in ("sequential", "vmap"):
        sp = S.parse_spec({**doc, "execution": execution})
        by[execution] = {k: np.full(pl.n_runs, np.nan) for k in S.METRICS}
        for idx, vals in S.execute(sp, pl, groups, group_of, np.zeros(pl.n_runs, bool)):
            for k, v in vals.items():
                by[execution][k][idx] = v
    got = by["sequential"]
    for k in S.METRICS:  # one vmapped program against one program per run: rounding only
        np.testing.assert_allclose(by["vmap"][k], got[k], rtol=1e-9, err_msg=k)
    from jaxcal.tune import window

    w = window(ds, 12)
    for r in range(pl.n_runs):
        p = {**FIXED, **extra, **{k: pl.values[k][r] for k in grid}}
        res, _ = run_pgp(w, {**p, "mirror": "off"}, "conf1")  # a sweep measures the filter (module doc)
        ev = evaluate_mesh(res, w)
        np.testing.assert_allclose(got["rmse_m"][r], ev["rmse_m"], rtol=1e-9)
        np.testing.assert_allclose(got["final_rmse_m"][r], ev["final_rmse_m"], rtol=1e-9)
        avail = np.isfinite(res.track_position).all(-1)
        a0 = ds.config("conf1")[0]
        assert got["localised"][r] == avail[-1].sum() - avail[-1][a0]
        assert np.isfinite(got["nlpl"][r])
    assert len(set(np.round(got["nlpl"], 9))) == pl.n_runs  # every value really ran


# one case: the compilations of the fast path dominate (parametric and the mixture kernel take the
# same execution path; their sweep metrics are checked against run_pgp in the tests above)
@pytest.mark.parametrize("method, range_model", [("pgp", "gaussian")])
def test_sequential_fast_path_equals_run_pgp_bit_for_bit(method, range_model):
    """CPU execution: every run is `run_pgp`'s windowed fast path, so the numbers are identical."""
    import jax

    from jaxcal.mesh import pgp
    from test_pgp_speed import FINE, mesh

    ds = mesh(k=20)
    swept = {"sigma_r": [0.3, 0.35], "sigma_v": [0.12, 0.2]}  # runs that take different branches
    fixed = {k: v for k, v in FINE.items() if k not in swept}
    fixed |= {"range_model": range_model, "window_small_m": 3.0}  # small, big windows, full grid
    doc = {
        "method": method,
        "batch_size": 3,  # the 2nd batch padded with copies (padding is not run sequentially)
        "params": fixed,
        "grid": swept,
        "scenarios": [{"file": "x.h5"}],
    }
    spec = S.parse_spec(doc)
    assert S.resolve_execution(spec.execution, "cpu") == "sequential"
    assert S.resolve_execution(spec.execution, "gpu") == "vmap"
    pl = S.plan(spec)
    groups, group_of = S.build_groups([(ds, None)], spec)
    got = {k: np.full(pl.n_runs, np.nan) for k in S.METRICS}
    ticks = []
    batches = S.execute(spec, pl, groups, group_of, np.zeros(pl.n_runs, bool), progress=ticks.append)
    for idx, vals in batches:
        for k, v in vals.items():
            got[k][idx] = v
    assert sum(ticks) == pl.n_runs == 4
    windowed = 0
    for r in range(pl.n_runs):
        p = {**fixed, **{k: pl.values[k][r] for k in swept}}
        res, _ = run_pgp(ds, {**p, "mirror": "off"}, None, mode=method)  # a sweep measures the filter
        ev = evaluate_mesh(res, ds)
        np.testing.assert_allclose(got["rmse_m"][r], ev["rmse_m"], rtol=1e-12)
        np.testing.assert_allclose(got["final_rmse_m"][r], ev["final_rmse_m"], rtol=1e-12)
        have = np.isfinite(res.track_position).all(-1)
        assert got["availability"][r] == np.delete(have, 0, axis=1).mean()  # a0 is node 0 here
        # bit for bit: the same chunks of the same programs on the same inputs as run_pgp
        cfg, prm, inp, lp0, _ = pgp.prepare(ds, pgp.PGPParams(**p), None, method)
        _, out = pgp.run_chunked(cfg, prm, inp, lp0)
        windowed += int(out.windowed.sum())
        truth = groups[0].truth[0]
        want = jax.tree.map(float, S._reduce_jit(out, prm, truth, groups[0].span_m))
        assert {k: got[k][r] for k in S.METRICS} == want
    if method == "pgp":
        assert windowed > 0  # the fast path really ran
        # the accelerator execution (vmapped, branch decided per step for the whole batch,
        # `mesh.lockstep`) equals it up to rounding
        vm = S.parse_spec({**doc, "execution": "vmap"})
        alt = {k: np.full(pl.n_runs, np.nan) for k in S.METRICS}
        for idx, vals in S.execute(vm, pl, groups, group_of, np.zeros(pl.n_runs, bool)):
            for k, v in vals.items():
                alt[k][idx] = v
        for k in S.METRICS:
            np.testing.assert_allclose(alt[k], got[k], rtol=1e-9, err_msg=k)


@pytest.mark.parametrize("execution", ["vmap", "sequential"])
def test_no_recompilation_across_values(monkeypatch, execution):
    from jaxcal.mesh import pgp

    if execution == "vmap":
        fns = [eqx.filter_jit(eqx.debug.assert_max_traces(S._batched, max_traces=1))]
        monkeypatch.setattr(S, "run_batch", fns[0])
    else:  # one run at a time: the filter (dense: one scan) and the metrics compile once
        fns = [
            eqx.filter_jit(eqx.debug.assert_max_traces(pgp.filter_epochs, max_traces=1)),
            eqx.filter_jit(eqx.debug.assert_max_traces(S.reduce_metrics, max_traces=1)),
        ]
        monkeypatch.setattr(pgp, "run_filter", fns[0])
        monkeypatch.setattr(pgp.epochs, "run_filter", fns[0])  # what `pgp.run_chunked` calls
        monkeypatch.setattr(S, "_reduce_jit", fns[1])
    doc = {
        "epochs": 5,
        "batch_size": 2,
        "execution": execution,
        "params": FIXED,
        "grid": {"sigma_r": [0.3, 0.6, 0.9, 1.2, 1.5, 2.0], "sigma_v": [0.2, 0.5]},
        "scenarios": [{"simulate": "small", "config": "conf1", "seeds": [0]}],
    }
    spec = S.parse_spec(doc)
    pl = S.plan(spec)
    groups, group_of = S.build_groups([(simulate("small", 0), "conf1")], spec)
    batches = list(S.execute(spec, pl, groups, group_of, np.zeros(pl.n_runs, bool)))
    assert len(batches) == 6 and sum(b[0].size for b in batches) == 12
    assert [eqx.debug.get_num_traces(f) for f in fns] == [1] * len(fns)


@pytest.mark.parametrize(
    "doc, fragment",
    [
        ({"grid": {"cell_m": [1.0, 2.0]}, "scenarios": [{"simulate": "small"}]}, "only"),
        ({"grid": {"sigma_r": [-1.0]}, "scenarios": [{"simulate": "small"}]}, "sigma_r"),
        ({"grid": {"sigma_r": [1.0]}, "scenarios": []}, "scenarios"),
        ({"scenarios": [{"simulate": "small", "file": "x.h5"}]}, "exactly one"),
        ({"colour": 1, "scenarios": [{"simulate": "small"}]}, "unknown"),
        ({"execution": "fast", "scenarios": [{"simulate": "small"}]}, "execution"),
        (
            {
                "params": {"sigma_r": 1.0},
                "grid": {"sigma_r": [1.0]},
                "scenarios": [{"simulate": "small"}],
            },
            "both",
        ),
    ],
)
def test_bad_spec(doc, fragment):
    with pytest.raises(JaxcalError, match=fragment):
        S.parse_spec(doc)


def _env(tmp_path, **extra):
    e = {
        "JAX_COMPILATION_CACHE_DIR": str(tmp_path.parent / "jaxcache"),
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
    }
    e.update(extra)
    return e


def _metrics(path):
    from jaxcal.commands.sweep import read_store

    _, runs, metrics, done = read_store(str(path))
    return runs, metrics, done


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """One uninterrupted single-device sweep (CLI, float32)."""
    d = tmp_path_factory.mktemp("sweep")
    spec = d / "spec.toml"
    spec.write_text(SPEC)
    out = d / "ref.h5"
    proc = run_cli("sweep", spec, "-o", out, "--json", env=_env(d))
    assert proc.returncode == 0, proc.stderr
    runs, metrics, done = _metrics(out)
    assert done.all() and len(done) == N_RUNS
    assert "ETA" in proc.stderr
    return spec, runs, metrics


def _same(a, b):
    for k in S.METRICS:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_kill_and_resume_equals_uninterrupted(reference, tmp_path):
    spec, runs_ref, ref = reference
    out = tmp_path / "s.h5"
    env = dict(os.environ, JAX_PLATFORMS="cpu", **_env(spec.parent))
    proc = subprocess.Popen(
        [sys.executable, "-m", "jaxcal.cli", "sweep", str(spec), "-o", str(out), "--throttle", "2"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 120
    n_done = 0
    while time.time() < deadline:
        if out.exists():
            n_done = int(_metrics(out)[2].sum())  # every state on disk is a complete file
            if n_done >= 2:
                break
        time.sleep(0.1)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    runs, part, done = _metrics(out)
    assert 2 <= done.sum() < N_RUNS, done
    n_done = int(done.sum())
    np.testing.assert_array_equal(np.isnan(part["nlpl"]), ~done)
    # the progress bar (forced on: stderr is a pipe here) counts the runs left; stdout stays JSON
    res = run_cli("sweep", spec, "-o", out, "--json", env=_env(spec.parent, JAXCAL_PROGRESS="1"))
    assert res.returncode == 0, res.stderr
    import json

    summary = json.loads(res.stdout)
    assert summary["computed"] == N_RUNS - n_done and summary["resumed"] == n_done
    left = N_RUNS - n_done
    import re

    assert re.search(rf"\b[1-9]\d*/{left} \[", res.stderr) and "run" in res.stderr, res.stderr
    runs, metrics, done = _metrics(out)
    assert done.all()
    _same(metrics, ref)
    for k in runs_ref:
        np.testing.assert_array_equal(runs[k], runs_ref[k])
    # finished: a third call computes nothing; another spec on the same file is refused
    again = run_cli("sweep", spec, "-o", out, "--json", env=_env(spec.parent))
    assert json.loads(again.stdout)["computed"] == 0
    other = tmp_path / "other.toml"
    other.write_text(SPEC.replace("[0.5, 0.9]", "[0.5, 0.8]"))
    assert_one_line_error(run_cli("sweep", other, "-o", out), "different sweep spec")


def test_four_virtual_devices_equal_one(reference, tmp_path):
    spec, _, ref = reference
    out = tmp_path / "d4.h5"
    proc = run_cli(
        "sweep",
        spec,
        "-o",
        out,
        "--json",
        "--quiet",
        # added to the run's own flags (scripts/test.sh sets some), so both runs compile alike
        env=_env(spec.parent, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4"),
    )
    assert proc.returncode == 0, proc.stderr
    assert '"devices": 4' in proc.stdout
    assert "runs/s" not in proc.stderr and "run/s" not in proc.stderr  # --quiet: no progress
    _same(_metrics(out)[1], ref)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_equal_one(reference, tmp_path):
    spec, _, ref = reference
    out = tmp_path / "p2.h5"
    addr = f"127.0.0.1:{_free_port()}"
    env = dict(os.environ, JAX_PLATFORMS="cpu", **_env(spec.parent))
    env.pop("JAXCAL_DEBUG", None)
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "jaxcal.cli",
                "sweep",
                str(spec),
                "-o",
                str(out),
                "--coordinator",
                addr,
                "--num-processes",
                "2",
                "--process-id",
                str(i),
                "--json",
            ],
            env=env,
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    for p, (_so, se) in zip(procs, outs, strict=True):
        assert p.returncode == 0, se
    # only process 0 writes and reports (gloo prints its own connection line on stdout)
    assert '"processes": 2' in outs[0][0] and "{" not in outs[1][0]
    _same(_metrics(out)[1], ref)


def test_site_wider_than_radio_range_runs_as_calibrate(rng, caplog):
    """A dataset that `calibrate --method pgp` runs on node-local grids (issue #26): every sweep cell
    is that calibrate run (node-local grids, fitted range offset), not the global grid's."""
    import logging

    from jaxcal.mesh import pgp
    from test_pgp_local import SMALL, site

    wide = site(rng)
    small = simulate("small", 3)
    doc = {
        "params": SMALL,
        "grid": {"sigma_r": [0.3, 0.6]},
        "scenarios": [{"file": "wide.h5"}, {"file": "small.h5", "config": "conf1"}],
    }
    spec = S.parse_spec(doc)
    pl = S.plan(spec)
    with caplog.at_level(logging.WARNING, logger="jaxcal"):
        groups, group_of = S.build_groups([(wide, None), (small, "conf1")], spec)
    assert isinstance(groups[group_of[0]], S.LocalGroup) and not isinstance(groups[group_of[1]], S.LocalGroup)
    assert len([m for m in caplog.messages if "node-local" in m and "nlpl" in m]) == 1
    got = {k: np.full(pl.n_runs, np.nan) for k in S.METRICS}
    for idx, vals in S.execute(spec, pl, groups, group_of, np.zeros(pl.n_runs, bool)):
        for k, v in vals.items():
            got[k][idx] = v
    assert np.isfinite(got["final_rmse_m"]).all()
    for r in np.flatnonzero(pl.dataset_of == 0):
        p = {**SMALL, "sigma_r": pl.values["sigma_r"][r]}
        assert pgp.uses_local(wide, p)
        ev = evaluate_mesh(pgp.calibrate(wide, p), wide)
        np.testing.assert_allclose(got["final_rmse_m"][r], ev["final_rmse_m"], atol=1e-6)
        np.testing.assert_allclose(got["rmse_m"][r], ev["rmse_m"], atol=1e-6)
        assert np.isnan(got["nlpl"][r])
    assert np.isfinite(got["nlpl"][pl.dataset_of == 1]).all()
