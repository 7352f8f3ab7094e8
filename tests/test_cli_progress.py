"""Stage-level progress of the long commands (#21 item 3): the core reports each stage through its
`progress` callback, and the command line shows a bar only on a terminal (or JAXCAL_PROGRESS=1)."""

from __future__ import annotations

import numpy as np

import jaxcal.mesh.batch as B
from test_batch import FAST, random_geometry, ranges_of


def test_batch_reports_every_stage_once(rng):
    truth = random_geometry(rng, 2)
    r = ranges_of(truth, noise=0.05, rng=rng)
    p = B.BatchParams(**FAST)
    calls = []
    sol = B.solve(r, (0, 1, 2), p, progress=calls.append)
    assert calls == [1] * B.stage_count(p) and B.stage_count(p) == 4  # fit, relocation, all-ranges, covariance
    assert np.isfinite(sol.position).all()


def test_report_shows_a_section_bar_only_when_asked(tmp_path):
    from conftest import run_cli
    from jaxcal.commands.sweep import FORMAT, _write_store

    s, t = np.meshgrid([0.2, 0.4], [0.8, 0.9], indexing="ij")
    n = s.size
    _write_store(
        tmp_path / "sweep.h5",
        {
            "format": FORMAT,
            "spec_id": "x",
            "spec_toml": "",
            "method": "pgp",
            "epochs": -1,
            "fixed_params": "{}",
            "swept": "sigma_r,tau",
        },
        {
            "scenario": np.array(["small"] * n),
            "config": np.array([""] * n),
            "seed": np.zeros(n, np.int64),
            "param_sigma_r": s.ravel(),
            "param_tau": t.ravel(),
        },
        {"rmse_m": np.array([0.5, 0.4, 0.3, 0.6]), "final_rmse_m": np.full(n, 0.3), "nlpl": np.ones(n)},
        np.ones(n, bool),
    )
    shown = run_cli("report", tmp_path / "sweep.h5", "-o", tmp_path / "a", env={"JAXCAL_PROGRESS": "1"})
    assert shown.returncode == 0, shown.stderr
    assert "report: 100%" in shown.stderr.replace("\r", "\n") and "1/1" in shown.stderr
    quiet = run_cli("report", tmp_path / "sweep.h5", "-o", tmp_path / "b", "--quiet", env={"JAXCAL_PROGRESS": "1"})
    assert quiet.returncode == 0 and quiet.stderr == "" and quiet.stdout == ""
    assert (tmp_path / "b" / "index.html").is_file()
