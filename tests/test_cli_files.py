"""Imports cross-check what they join; `info` and `validate` work on every file jaxcal writes (issue #25,
items 5 and 6)."""

from __future__ import annotations

import json

import numpy as np

from conftest import assert_one_line_error, mesh_of, run_cli, shared_path
from jaxcal.io import hdf5

_YAML = (
    "n_networks: 1\nnetwork0:\n  n_anchors: 4\n"
    "  anchor0_id: A\n  anchor1_id: B\n  anchor2_id: C\n  anchor3_id: D\n"
    "  gt:\n    anchor0_coordinates: [0, 0, 0]\n    anchor1_coordinates: [{b}, 0, 0]\n"
    "    anchor2_coordinates: [0, 4, 0]\n    anchor3_coordinates: [3, 4, 0]\n"
)


def _dwm_scenario(tmp_path, rng, extra_node: bool = False):
    """Four DWM1001 range files of a 3 x 4 m rectangle (noise 5 cm), as the dwm1001-autocal layout."""
    pos = np.array([[0, 0], [3, 0], [0, 4], [3, 4]], float)
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    scen = tmp_path / "scen"
    scen.mkdir()
    for i, node in enumerate("ABCD"):
        rows = d[i][None] + rng.normal(0, 0.05, (30, 4))
        rows[:, i] = -1
        (scen / f"{node}_ranging_data.txt").write_text("\n".join(" ".join(f"{v:.3f}" for v in r) for r in rows))
    if extra_node:
        (scen / "E_ranging_data.txt").write_text("1 2 3 4\n")
    return scen


def test_import_refuses_a_layout_that_does_not_fit(tmp_path, rng):
    scen = _dwm_scenario(tmp_path, rng)
    good, bad = tmp_path / "good.yaml", tmp_path / "bad.yaml"
    good.write_text(_YAML.format(b=3))
    bad.write_text(_YAML.format(b=9))  # B 6 m off: another site
    p = run_cli("import", "dwm1001-autocal", scen, good, "-o", tmp_path / "g.h5", "--json")
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["layout_median_m"] < 0.1
    p = run_cli("import", "dwm1001-autocal", scen, bad, "-o", tmp_path / "b.h5")
    assert_one_line_error(p, "median |range - layout distance|")
    assert not (tmp_path / "b.h5").exists()
    p = run_cli("import", "dwm1001-autocal", scen, bad, "-o", tmp_path / "b.h5", "--force")
    assert p.returncode == 0 and "warning (--force)" in p.stdout
    v = run_cli("validate", tmp_path / "b.h5", "--json")
    j = json.loads(v.stdout)
    assert v.returncode == 0 and j["status"] == "warning" and "median" in j["warnings"][0]
    assert j["layout_median_m"] > 1.0
    assert json.loads(run_cli("validate", tmp_path / "g.h5", "--json").stdout)["status"] == "valid"


def test_import_refuses_ids_that_do_not_match(tmp_path, rng):
    scen = _dwm_scenario(tmp_path, rng, extra_node=True)
    (tmp_path / "l.yaml").write_text(_YAML.format(b=3))
    p = run_cli("import", "dwm1001-autocal", scen, tmp_path / "l.yaml", "-o", tmp_path / "x.h5")
    assert_one_line_error(p, "node ids do not match")
    assert "E" in p.stderr
    p = run_cli("import", "dwm1001-autocal", scen, tmp_path / "l.yaml", "-o", tmp_path / "x.h5", "--force")
    assert p.returncode == 0, p.stderr


def test_real_ranges_with_another_sites_layout(tmp_path):
    root = shared_path("datasets", "dwm1001-autocal")
    ranges = root / "srvlab_ground"
    p = run_cli(
        "import", "dwm1001-autocal", ranges, root / "nodes_cfg" / "campus_sport.yaml", "-o", tmp_path / "mixed.h5"
    )
    assert_one_line_error(p, "4.58 m")
    p = run_cli(
        "import",
        "dwm1001-autocal",
        ranges,
        root / "nodes_cfg" / "srvlab_ground.yaml",
        "-o",
        tmp_path / "srv.h5",
        "--json",
    )
    assert p.returncode == 0 and json.loads(p.stdout)["layout_median_m"] < 0.2
    info = run_cli("info", tmp_path / "srv.h5")
    assert "time: epoch index 1..99" in info.stdout
    assert json.loads(run_cli("info", tmp_path / "srv.h5", "--json").stdout)["time_is_index"] is True


def test_validate_checks_truth_of_any_file(tmp_path, rng):
    from conftest import random_layout

    pos, d = random_layout(rng, 5, 10.0)
    r = np.broadcast_to(d, (20, 5, 5)) + rng.normal(0, 0.05, (20, 5, 5))
    hdf5.write(tmp_path / "ok.h5", mesh_of(r, pos))
    wrong = pos.copy()
    wrong[3] += 5.0
    hdf5.write(tmp_path / "wrong.h5", mesh_of(r, wrong[[1, 0, 2, 4, 3]]))
    ok = run_cli("validate", tmp_path / "ok.h5")
    assert ok.returncode == 0 and "valid jaxcal mesh" in ok.stdout and "warning" not in ok.stdout
    w = run_cli("validate", tmp_path / "wrong.h5")
    assert w.returncode == 0 and "warning: median |range - layout distance|" in w.stdout
    assert "time: 0.000" in run_cli("info", tmp_path / "ok.h5").stdout  # real seconds: not an index


def test_info_and_validate_on_every_kind_of_file(tmp_path):
    from jaxcal.commands.sweep import FORMAT, _write_store
    from jaxcal.io.recorder import JournalWriter

    n = 4
    _write_store(
        tmp_path / "sweep.h5",
        {
            "format": FORMAT,
            "spec_id": "x",
            "spec_toml": "",
            "method": "pgp",
            "epochs": -1,
            "fixed_params": "{}",
            "swept": "sigma_r",
        },
        {
            "scenario": np.array(["small"] * n),
            "config": np.array([""] * n),
            "seed": np.arange(n),
            "param_sigma_r": np.array([0.1, 0.2, 0.1, 0.2]),
        },
        {"rmse_m": np.array([0.5, 0.4, np.nan, np.nan])},
        np.array([True, True, False, False]),
    )
    j = JournalWriter(tmp_path / "rec.h5.journal", {"protocol": "nlink"})
    j.append(b"\x55\x01", 0.5)
    j.close()
    (tmp_path / "p.json").write_text(
        json.dumps({"params": {"sigma_r": 0.4, "tau": 0.8}, "tuning": {"method": "pgp", "dataset": "d"}})
    )
    (tmp_path / "bad.json").write_text(json.dumps({"params": {"nosuch": 1}, "tuning": {"method": "pgp"}}))

    s = json.loads(run_cli("info", tmp_path / "sweep.h5", "--json").stdout)
    assert s["format"] == "sweep" and s["runs"] == 4 and s["done"] == 2 and s["swept"] == {"sigma_r": [0.1, 0.2]}
    assert s["metrics"]["rmse_m"] == [0.4, 0.5]
    assert "2/4 runs done" in run_cli("info", tmp_path / "sweep.h5").stdout
    v = json.loads(run_cli("validate", tmp_path / "sweep.h5", "--json").stdout)
    assert v == {"file": str(tmp_path / "sweep.h5"), "format": "sweep", "status": "valid", "warnings": []}
    jn = json.loads(run_cli("info", tmp_path / "rec.h5.journal", "--json").stdout)
    assert jn["format"] == "journal" and jn["frames"] == 1 and jn["header"]["protocol"] == "nlink"
    assert run_cli("validate", tmp_path / "rec.h5.journal").returncode == 0
    pj = json.loads(run_cli("info", tmp_path / "p.json", "--json").stdout)
    assert pj["format"] == "params" and pj["params"]["sigma_r"] == 0.4
    assert "valid jaxcal parameter file" in run_cli("validate", tmp_path / "p.json").stdout
    assert_one_line_error(run_cli("validate", tmp_path / "bad.json"), "unknown parameter 'nosuch'")
    q = run_cli("validate", tmp_path / "p.json", "--quiet")
    assert q.returncode == 0 and q.stdout == "" and q.stderr == ""
