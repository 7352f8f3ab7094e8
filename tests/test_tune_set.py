"""Tuning on a set of recordings: the objective is the mean of the recordings' objectives, the guard
pools their units and refuses when one recording gets clearly worse, the CLI's bad input."""

from __future__ import annotations

import dataclasses
import json

import equinox as eqx
import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli
from jaxcal import tune as T
from jaxcal import tune_eval as E
from jaxcal.io import hdf5
from jaxcal.mesh.pgp import PGPParams
from test_tune import SMALL, make_mesh


def named(ds, name):
    return dataclasses.replace(ds, name=name)


def test_set_objective_is_the_mean_of_the_recordings():
    """Two recordings of different layouts and lengths: the set's objective (evidence, the default)
    at any theta is the mean of the two single-recording objectives (each recording counts once)."""
    a, b = make_mesh(n=6, k=5, seed=1), make_mesh(n=6, k=7, seed=2)
    p = PGPParams(**SMALL)
    pa, _ = T.make_problem(a, p, None, "evidence", tau_temp=0.1)
    pb, _ = T.make_problem(b, p, None, "evidence", tau_temp=0.1)
    f = eqx.filter_jit(T.objective)  # one compile per problem (eager scans compile op by op)
    for theta in (T.theta_of(0.8, 0.7, 0.6, pa.logpost0.dtype), T.theta_of(0.5, 0.4, 0.8, pa.logpost0.dtype)):
        va, vb = float(f(theta, pa)), float(f(theta, pb))
        assert np.isfinite(va) and np.isfinite(vb) and va != pytest.approx(vb)
        assert float(f(theta, (pa, pb))) == pytest.approx((va + vb) / 2, rel=1e-12)


@pytest.mark.parametrize("worse", [True, False])
def test_set_guard_refuses_when_one_recording_gets_clearly_worse(monkeypatch, rng, worse):
    """Recording A gains clearly, B loses a little with a small scatter (its own t << -1) or is
    merely mixed (t = 0): the pooled gain passes t > 1 and the mean falls in both cases, but a
    recording clearly worse on its own keeps the start, and the one-line summary names it."""
    from jaxcal.commands.tune import _summary

    a, b = named(make_mesh(n=7, k=6, seed=3), "A.h5"), named(make_mesh(n=7, k=6, seed=4), "B.h5")
    base = {"A.h5": rng.uniform(0.5, 1.0, 6), "B.h5": rng.uniform(0.5, 1.0, 6)}  # 4 non-anchor nodes: 6 pairs

    def centred(sd):
        x = rng.normal(0.0, sd, 6)
        return x - x.mean()

    gain = {"A.h5": 0.3 + centred(0.05), "B.h5": (-0.02 + centred(0.005)) if worse else centred(0.05)}

    def pair_errors(dataset, params, config, *args, **kw):
        moved = float(np.asarray(params.sigma_r)) != pytest.approx(SMALL["sigma_r"])
        return base[dataset.name] - (gain[dataset.name] if moved else 0.0)

    monkeypatch.setattr(E, "heldout_pair_errors", pair_errors)
    seen = []

    def fake_bfgs(theta0, prob, *args, **kw):
        seen.append(prob)
        return theta0.at[0].add(0.1), 1, True, "ok", 1.0, 0.5

    monkeypatch.setattr(T, "_bfgs", fake_bfgs)
    res = T.tune([a, b], SMALL, None, objective_name="evidence", tau_temp=0.1)
    assert isinstance(seen[0], tuple) and len(seen[0]) == 2  # the gradient phase saw both
    st = res.settings
    assert res.hard_key == "heldout_m" and res.hard_after["heldout_m"] < res.hard_before["heldout_m"]
    pooled = np.concatenate([base["A.h5"], base["B.h5"]])
    moved = pooled - np.concatenate([gain["A.h5"], gain["B.h5"]])
    assert st["guard_gain_t"] == pytest.approx(E.paired_gain_t(pooled, moved), rel=1e-12) and st["guard_gain_t"] > 1
    own = {r["dataset"]: r["guard_gain_t"] for r in st["recordings"]}
    assert own["A.h5"] > 1 and (own["B.h5"] < -T.GUARD_T) == worse
    assert res.accepted == (not worse) and st["worse_recording"] == ("B.h5" if worse else "")
    assert res.params == (res.start if worse else res.tuned)
    mean = np.mean([r["hard_before"]["heldout_m"] for r in st["recordings"]])
    assert res.hard_before["heldout_m"] == pytest.approx(mean, rel=1e-12)
    line = _summary(res, "evidence", "p.json")
    assert "\n" not in line and "on 2 recordings (mean)" in line
    if worse:
        assert "B.h5 got clearly worse" in line and f"t = {own['B.h5']:.2f}" in line and "kept the start" in line
    else:
        assert "tuned values written" in line


def test_one_recording_in_a_list_is_the_one_recording_tune(monkeypatch):
    """`tune([ds])` = `tune(ds)`: same problem handed to the optimiser, same guard figures."""
    ds = make_mesh(n=6, k=5, seed=5)
    seen = []
    monkeypatch.setattr(
        T, "_bfgs", lambda theta0, prob, *a, **k: seen.append(prob) or (theta0.at[1].add(0.2), 1, True, "ok", 1.0, 0.5)
    )
    one = T.tune(ds, SMALL, None, objective_name="truth", tau_temp=0.1)
    lst = T.tune([ds], SMALL, None, objective_name="truth", tau_temp=0.1)
    assert all(isinstance(p, T.Problem) for p in seen)
    assert (one.hard_before, one.hard_after, one.accepted, one.params) == (
        lst.hard_before,
        lst.hard_after,
        lst.accepted,
        lst.params,
    )


def test_cli_set_bad_input_is_one_line_before_any_work(tmp_path):
    f, small = tmp_path / "a.h5", tmp_path / "s.h5"
    hdf5.write(f, make_mesh(n=6, k=4, seed=1))
    hdf5.write(small, make_mesh(n=4, k=4, seed=2))
    out = tmp_path / "p.json"
    assert_one_line_error(run_cli("tune", f, tmp_path / "missing.h5", "-o", out), "missing.h5")
    assert_one_line_error(run_cli("tune", f, f, "-o", out), "given twice")
    # evidence holds pairs out only with >= 5 nodes: a 4-node file would mix metres and nats
    assert_one_line_error(run_cli("tune", f, small, "-o", out), "fewer than 5 nodes")
    assert not out.exists()


def test_cli_tune_on_a_set(tmp_path):
    paths = []
    for i, k in enumerate((5, 6)):
        paths.append(tmp_path / f"m{i}.h5")
        hdf5.write(paths[-1], named(make_mesh(n=6, k=k, seed=10 + i), "site"))  # one name: called by their files
    sets = [a for k, v in SMALL.items() if k != "cell_m" for a in ("--set", f"{k}={v}")]
    out = tmp_path / "p.json"
    proc = run_cli("tune", *paths, "--max-steps", "2", "-o", out, *sets, env={"JAXCAL_PROGRESS": "1"})
    assert proc.returncode == 0, proc.stderr
    line = proc.stdout.strip()
    assert "\n" not in line and line.startswith("tune evidence on 2 recordings (mean):")
    assert "gradient on 11 epochs in all" in line and "recording 2/2" in proc.stderr
    t = json.loads(out.read_text())["tuning"]
    assert t["dataset"] == [str(p) for p in paths] and [r["epochs"] for r in t["settings"]["recordings"]] == [5, 6]
