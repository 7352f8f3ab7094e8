"""`jaxcal demo`: the embedded dataset is the simulator's output, and the demo runs end to end."""

from __future__ import annotations

import json

import numpy as np

from conftest import run_cli
from jaxcal.commands import demo
from jaxcal.io import hdf5
from jaxcal.sim.mesh import simulate


def test_embedded_dataset_equals_resimulation():
    path = demo.embedded_dataset_path()
    assert path.is_file(), f"{path} is missing: run `jaxcal simulate mesh -o data/torgau.h5 --seed {demo.DEMO_SEED}`"
    shipped = hdf5.read(path)
    fresh = simulate(demo.DEMO_SCENARIO, seed=demo.DEMO_SEED)
    np.testing.assert_array_equal(shipped.range, fresh.range)
    np.testing.assert_array_equal(shipped.truth, fresh.truth)
    np.testing.assert_array_equal(shipped.los, fresh.los)
    np.testing.assert_array_equal(shipped.time, fresh.time)
    assert shipped.configs == fresh.configs and shipped.node_ids == fresh.node_ids


def test_demo_smoke(tmp_path):
    out = tmp_path / "demo"
    p = run_cli("demo", "-o", out, "--methods", "cf")
    assert p.returncode == 0, p.stderr
    text = p.stdout
    assert "paper LOS" in text and "Median (m)" in text and "== cf ==" in text
    for nid in ("D5B4", "4503"):
        assert nid in text
    summary = json.loads((out / "summary.json").read_text())
    runs = {r["config"]: r for r in summary["runs"]}
    assert set(runs) == {"conf1", "conf2"}
    for r in runs.values():
        assert (out / r["output"].split("/")[-1]).is_file()
        avail = [n["availability"] for n in r["nodes"]]
        assert all(0.0 <= a <= 1.0 for a in avail) and max(avail) > 0.5
        assert r["aligned_rmse_m"] < 5.0
    assert summary["groups"]["nlos"]["median_m"] > summary["groups"]["los"]["median_m"]


def test_demo_rejects_unknown_method(tmp_path):
    p = run_cli("demo", "-o", tmp_path, "--methods", "nope")
    assert p.returncode == 2 and "not registered" in p.stderr and "Traceback" not in p.stderr
