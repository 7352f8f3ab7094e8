"""Importers: real recordings in ../shared/datasets (skipped when absent) and small synthetic files.

Expected values come from independent parsing of the raw files with the csv module (never from the
importer code). Every real dataset must agree with its truth: median(range - true distance) within
0.5 m, which fails for a wrong column order, unit or quaternion reading.
"""

from __future__ import annotations

import csv
import datetime as dt
import math

import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli, shared_path
from jaxcal.data import MeshDataset, TrajectoryDataset, mesh_true_distances
from jaxcal.errors import JaxcalError
from jaxcal.io import hdf5
from jaxcal.io.importers import IMPORTERS, import_recording

DWM = ("dwm1001-autocal",)
SCENARIOS = [
    ("campus_sport/rich_samples", "campus_sport"),
    ("srvlab_ground", "srvlab_ground"),
    ("3D_distribution", "3D_distribution"),
]


def _roundtrip(ds, tmp_path):
    out = tmp_path / "rt.h5"
    hdf5.write(out, ds)
    back = hdf5.read(out)
    assert type(back) is type(ds) and back.name == ds.name
    for f in (
        "range",
        "time",
        "truth",
        "range_time",
        "pose_time",
        "pose_position",
        "pose_orientation",
        "range_anchor",
        "range_tag",
        "anchor_truth",
        "lever_arm",
        "range_los",
        "fp_rssi",
    ):
        a, b = getattr(ds, f, None), getattr(back, f, None)
        if a is not None:
            np.testing.assert_array_equal(a, b)
    assert back.source == ds.source and back.license == ds.license and back.description == ds.description
    return back


def _quat_apply(q, v):
    """Rotate vectors v (R, 3) by unit quaternions q (R, 4) scalar last: v + 2 u x (u x v + w v)."""
    u, w = q[:, :3], q[:, 3:]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def _traj_residuals(ds: TrajectoryDataset, offset: float = 0.0, every: int = 1):
    """range - true distance with poses interpolated at range time + offset (np.interp), lever arms applied."""
    t = ds.range_time[::every] + offset
    m = (t >= ds.pose_time[0]) & (t <= ds.pose_time[-1])
    t = t[m]
    a, g = ds.range_anchor[::every][m], ds.range_tag[::every][m]
    pos = np.stack([np.interp(t, ds.pose_time, ds.pose_position[:, k]) for k in range(3)], axis=1)
    lever = ds.lever_arm[g]
    if ds.pose_orientation is not None:
        idx = np.clip(np.searchsorted(ds.pose_time, t), 0, ds.pose_time.size - 1)  # nearest-after sample
        lever = _quat_apply(ds.pose_orientation[idx], lever)
    d = np.linalg.norm(pos + lever - ds.anchor_truth[a], axis=1)
    return ds.range[::every][m] - d, a * len(ds.tag_ids) + g


# ---------------------------------------------------------------- generic csv (synthetic)


def test_csv_synthetic(tmp_path):
    p = tmp_path / "ranges.csv"
    p.write_text(
        "time,from,to,range,los\n"
        "0.0,n2,n0,1.5,1\n"
        "0.0,n0,n2,1.6,1\n"
        "0.0,n0,n1,2.0,0\n"
        "0.5,n1,n0,2.1,1\n"
        "0.5,n1,n2,abc,1\n"  # non-numeric: skipped
        "0.5,n1,n1,1.0,1\n"  # self range: skipped
        "0.5,n2,n0,-1.0,1\n"  # negative: skipped
        "1.0,n0,n1,2.2,1\n"  # link n0->n1 now mixed -> -1
        "1.0,n0,n1,2.3,1\n"  # duplicate: last kept
        "1.0,n2,n1\n"  # wrong field count: skipped
    )
    ds = import_recording("csv", p)
    assert isinstance(ds, MeshDataset)
    assert ds.node_ids == ("n2", "n0", "n1")  # order of first appearance
    np.testing.assert_array_equal(ds.time, [0.0, 0.5, 1.0])
    i = {n: k for k, n in enumerate(ds.node_ids)}
    assert ds.range[0, i["n2"], i["n0"]] == np.float32(1.5)
    assert ds.range[0, i["n0"], i["n2"]] == np.float32(1.6)
    assert ds.range[1, i["n1"], i["n0"]] == np.float32(2.1)
    assert ds.range[2, i["n0"], i["n1"]] == np.float32(2.3)
    assert np.isfinite(ds.range).sum() == 5
    assert ds.los[i["n2"], i["n0"]] == 1 and ds.los[i["n0"], i["n1"]] == -1 and ds.los[i["n1"], i["n2"]] == -1
    assert "skipped 4 row(s)" in ds.description and "1 duplicate" in ds.description
    _roundtrip(ds, tmp_path)


def test_csv_without_los_has_no_los(tmp_path):
    p = tmp_path / "r.csv"
    p.write_text("time,from,to,range\n0,a,b,1\n0,b,c,2\n1,c,a,3\n")
    ds = import_recording("csv", p, name="x")
    assert ds.los is None and ds.name == "x" and ds.range.shape == (2, 3, 3)


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("time,from,range\n0,a,1\n", "missing column 'to'"),
        ("time,from,to,range\n0,a,b,x\n1,a,b,y\n", ":2:"),
        ("", "empty"),
        ("time,from,to,range\n", "no data rows"),
    ],
)
def test_csv_bad_files_raise_one_line(tmp_path, text, fragment):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(JaxcalError) as e:
        import_recording("csv", p)
    msg = str(e.value)
    assert "\n" not in msg and "bad.csv" in msg and fragment in msg


def test_unknown_importer_and_wrong_arity(tmp_path):
    with pytest.raises(JaxcalError, match="unknown importer"):
        import_recording("nope", "x")
    with pytest.raises(JaxcalError, match="takes 2 source"):
        import_recording("cuhksz", "x")
    with pytest.raises(JaxcalError, match="no such folder"):
        import_recording("hanyang", "/nonexistent/run")
    with pytest.raises(JaxcalError, match="no anchor file"):
        import_recording("hanyang", tmp_path)
    assert set(IMPORTERS) == {"dwm1001-autocal", "hymn", "cuhksz", "hanyang", "csv"}


# ---------------------------------------------------------------- dwm1001-autocal


def _dwm_expected(folder, yaml_path):
    import yaml

    cfg = yaml.safe_load(open(yaml_path))
    ids, gt = [], []
    for n in range(int(cfg["n_networks"])):
        net = cfg[f"network{n}"]
        for a in range(int(net["n_anchors"])):
            ids.append(net[f"anchor{a}_id"])
            gt.append(net["gt"][f"anchor{a}_coordinates"])
    raw = []
    for node in ids:
        with open(folder / f"{node}_ranging_data.txt") as f:
            raw.append([[float(v) for v in line.split()] for line in f if line.strip()])
    return ids, np.array(gt, float), np.array(raw)  # raw (N, K, N)


@pytest.mark.parametrize("scenario, cfg", SCENARIOS)
def test_dwm1001_real(scenario, cfg, tmp_path):
    root = shared_path("datasets", *DWM)
    folder, yaml_path = root / scenario, root / "nodes_cfg" / f"{cfg}.yaml"
    ds = import_recording("dwm1001-autocal", folder, yaml_path)
    ids, gt, raw = _dwm_expected(folder, yaml_path)
    assert ds.node_ids == tuple(ids)
    valid = raw >= 0
    assert np.isfinite(ds.range).sum() == valid.sum()
    kept_rows = valid.any(axis=(0, 2))
    assert ds.n_epochs == kept_rows.sum()
    np.testing.assert_array_equal(ds.time, np.flatnonzero(kept_rows))
    # spot values: file i, row k, column j is range i->j at epoch k
    k_row = int(np.flatnonzero(kept_rows)[1])
    e = int(np.searchsorted(ds.time, k_row))
    for i, j in [(0, 1), (3, 7), (8, 2)]:
        want = raw[i, k_row, j]
        got = ds.range[e, i, j]
        assert (np.isnan(got) and want < 0) or got == np.float32(want)
    planar = np.ptp(gt[:, 2]) == 0
    assert ds.truth.shape == (10, 2 if planar else 3)
    np.testing.assert_array_equal(ds.truth, gt[:, :2] if planar else gt)
    err = ds.range - mesh_true_distances(ds.truth)[None]
    assert abs(np.nanmedian(err)) < 0.5
    for _name, tri in ds.configs:
        assert len(set(tri)) == 3
    assert dict(ds.configs).keys() <= {"conf1", "conf2"}
    assert ds.license and "local use only" in ds.license and "esauortiz" in ds.source
    _roundtrip(ds, tmp_path)


def test_dwm1001_cleaning_on_synthetic_files(tmp_path):
    """Made-up numbers in the dwm1001 layout: -1, other negatives, absurd values, a bad line, a missing node."""
    (tmp_path / "cfg.yaml").write_text(
        "n_networks: 1\nnetwork0:\n  n_anchors: 4\n"
        "  anchor0_id: A\n  anchor1_id: B\n  anchor2_id: C\n  anchor3_id: D\n"
        "  gt:\n    anchor0_coordinates: [0, 0, 0]\n    anchor1_coordinates: [3, 0, 0]\n"
        "    anchor2_coordinates: [0, 4, 0]\n    anchor3_coordinates: [3, 4, 1]\n"
    )
    scen = tmp_path / "scen"
    scen.mkdir()
    (scen / "A_ranging_data.txt").write_text("-1 -1 -1 -1\n-1 3.1 -2.5 5.0\n-1 3.0 4.1 1e9\n")
    (scen / "B_ranging_data.txt").write_text("-1 -1 -1 -1\n2.9 -1 5.1 oops\n3.2 -1 5.0\n")
    (scen / "C_ranging_data.txt").write_text("-1 -1 -1 -1\n4.0 5.0 -1 3.1\n4.2 5.1 -1 3.3\n")
    ds = import_recording("dwm1001-autocal", scen, tmp_path / "cfg.yaml", name="syn")
    assert ds.n_epochs == 2 and ds.truth.shape == (4, 3)
    assert np.isnan(ds.range[0, 0, 2]) and np.isnan(ds.range[1, 0, 3])  # -2.5 and 1e9
    assert np.isnan(ds.range[:, 1]).all()  # both B lines malformed
    assert np.isnan(ds.range[:, 3]).all()  # no file for D
    assert ds.range[1, 0, 2] == np.float32(4.1)
    assert "2 negative or absurd" in ds.description and "2 malformed line" in ds.description
    assert "no file for node(s) D" in ds.description
    with pytest.raises(JaxcalError, match="no such yaml"):
        import_recording("dwm1001-autocal", scen, tmp_path / "none.yaml")


# ---------------------------------------------------------------- hymn


def _pylist(s):
    return [v.strip().strip("'") for v in s.strip()[1:-1].split(",")]


def test_hymn_real(tmp_path):
    root = shared_path("datasets", "hymn-torgau")
    ds = import_recording("hymn", root)
    with open(root / "data/processed/csv/uwb.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    n_finite = sum(not math.isnan(float(v)) for r in rows for v in _pylist(r["ranges"]))
    assert ds.n_ranges == n_finite
    dwells = 1 + sum(a["point_id"] != b["point_id"] for a, b in zip(rows, rows[1:], strict=False))
    assert ds.pose_time.shape[0] == 2 * dwells
    assert ds.anchor_ids == tuple(f"UWB_{i:02d}" for i in range(1, 11))
    with open(root / "data/reference/csv/anchor_coordinates.csv", newline="") as f:
        anc = {r["point_id"]: [float(r[c]) for c in ("X_LOCAL", "Y_LOCAL", "Z_LOCAL")] for r in csv.DictReader(f)}
    np.testing.assert_array_equal(ds.anchor_truth, [anc[a] for a in ds.anchor_ids])
    # first row: time, first range and tag position as in uwb.csv
    r0 = rows[0]
    assert ds.range_time[0] == int(r0["ts"]) / 1000
    first = next(
        (a, float(v)) for a, v in zip(_pylist(r0["anchor_ids"]), _pylist(r0["ranges"]), strict=False) if v != "nan"
    )
    assert ds.anchor_ids[ds.range_anchor[0]] == first[0] and ds.range[0] == np.float32(first[1])
    np.testing.assert_allclose(
        ds.pose_position[0], [float(r0[c]) for c in ("X_LOCAL_UWB", "Y_LOCAL_UWB", "Z_LOCAL_UWB")]
    )
    err, _ = _traj_residuals(ds)
    assert err.size == ds.n_ranges  # every range lies inside a dwell
    assert abs(np.median(err)) < 0.5
    assert "CC BY 4.0" in ds.license
    _roundtrip(ds, tmp_path)


# ---------------------------------------------------------------- cuhksz


def _wallclock(s):
    d, t = s.split(" ")
    h, m, sec = t.split(":")
    day = dt.datetime.strptime(d, "%Y-%m-%d").replace(tzinfo=dt.UTC).timestamp()
    return day + int(h) * 3600 + int(m) * 60 + float(sec)


@pytest.fixture(scope="module")
def cuhksz():
    d = shared_path("datasets", "cuhksz-planar", "Dynamic")
    return d, import_recording("cuhksz", d / "UWB_dynamic_exp_mid.csv", d / "motion_capture_dynamic_exp_mid.csv")


def _spread(err, group):
    """Median |err - median of its (anchor, tag) group|: the bias-free spread."""
    med = np.zeros(group.max() + 1)
    for g in np.unique(group):
        med[g] = np.median(err[group == g])
    return float(np.median(np.abs(err - med[group])))


def _best_offset(ds, every=7):
    offs = np.arange(-1.0, 0.61, 0.05)
    s = [_spread(*_traj_residuals(ds, o, every)) for o in offs]
    return float(offs[int(np.argmin(s))]), float(min(s))


def test_cuhksz_real(cuhksz, tmp_path):
    d, ds = cuhksz
    with open(d / "UWB_dynamic_exp_mid.csv", newline="") as f:
        uwb = list(csv.reader(f))
    vals = np.array([[float(v) if v else np.nan for v in r[1:]] for r in uwb])
    assert ds.n_ranges == int((vals > 0).sum())
    assert ds.range_time[0] == pytest.approx(_wallclock(uwb[0][0]), abs=1e-6)
    # first row, column order a0-t0, a0-t1, a0-t2, a1-t0, ...
    first = [(a, t, ds.range[k]) for k, (a, t) in enumerate(zip(ds.range_anchor[:24], ds.range_tag[:24], strict=False))]
    for a, t, r in first:
        assert r == np.float32(vals[0, 3 * a + t])
    with open(d / "motion_capture_dynamic_exp_mid.csv", newline="") as f:
        moc = list(csv.reader(f))[1:]
    mt = np.array([_wallclock(r[0]) for r in moc])
    assert ds.pose_time.shape[0] == 1 + int((np.diff(mt) > 0).sum())  # duplicate stamps dropped
    np.testing.assert_allclose(ds.pose_position[0], [float(v) for v in moc[0][1:4]])
    assert ds.anchor_truth.shape == (8, 3) and ds.lever_arm.shape == (3, 3)
    offset, spread = _best_offset(ds)
    assert -1.0 < offset < 0.5 and spread < 0.08
    err, _ = _traj_residuals(ds, offset)
    assert abs(np.median(err)) < 0.5
    assert ds.license.startswith("MIT")
    _roundtrip(ds, tmp_path)


def test_cuhksz_quaternion_reading_is_the_best_fit(cuhksz):
    """The stored orientation (README order then x-180deg) beats the raw README and scalar-last readings."""
    d, ds = cuhksz
    with open(d / "motion_capture_dynamic_exp_mid.csv", newline="") as f:
        moc = [r for r in list(csv.reader(f))[1:]]
    mt = np.array([_wallclock(r[0]) for r in moc])
    keep = np.concatenate([[True], np.diff(mt) > 0])
    q = np.array([[float(v) for v in r[4:8]] for r in moc])[keep]
    readings = {"readme_wxyz": q[:, [1, 2, 3, 0]], "scalar_last": q}
    stored = _best_offset(ds)[1]
    for name, qx in readings.items():
        other = _best_offset(ds.__class__(**{**_fields(ds), "pose_orientation": qx}))[1]
        assert stored < 0.8 * other, (name, stored, other)


def _fields(ds):
    import dataclasses

    return {f.name: getattr(ds, f.name) for f in dataclasses.fields(ds)}


# ---------------------------------------------------------------- hanyang


@pytest.mark.parametrize("run, los", [("LOS", 1), ("NLOS", 0)])
def test_hanyang_real(run, los, tmp_path):
    d = shared_path("datasets", "hanyang-outdoor", run, "Trajectory_A", "Case_1")
    ds = import_recording("hanyang", d)
    assert ds.anchor_ids == ("A3", "A5", "A9", "A12")
    with open(d / "trajectory.csv", newline="") as f:
        traj = list(csv.DictReader(f))
    t0, t1 = float(traj[0]["timestamp"]) / 1e9, float(traj[-1]["timestamp"]) / 1e9
    total = 0
    for a, aid in enumerate(ds.anchor_ids):
        with open(d / f"{aid}.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        ts = np.array([int(r["field.stamp"]) / 1e9 for r in rows])
        inside = (ts >= t0) & (ts <= t1)
        assert (ds.range_anchor == a).sum() == inside.sum()
        total += inside.sum()
        np.testing.assert_allclose(ds.anchor_truth[a], [float(rows[0][c]) for c in ("field.x", "field.y", "field.z")])
        r = rows[int(np.flatnonzero(inside)[0])]
        k = int(np.flatnonzero(ds.range_anchor == a)[0])
        assert ds.range[k] == np.float32(float(r["field.distanceFromTag"]))
        assert ds.fp_rssi[k] == np.float32(float(r["field.rssi_fp"]))
    assert ds.n_ranges == total and ds.pose_time.shape[0] == len(traj)
    assert np.all(ds.range_los == los)
    err, _ = _traj_residuals(ds)
    assert abs(np.median(err)) < 0.5
    assert ds.license == "Apache-2.0"
    _roundtrip(ds, tmp_path)


# ---------------------------------------------------------------- command line


def test_cli_import_csv_and_real(tmp_path):
    p = tmp_path / "r.csv"
    p.write_text("time,from,to,range\n0,a,b,1\n0,b,c,2\n1,c,a,3\n")
    out = tmp_path / "r.h5"
    proc = run_cli("import", "csv", p, "-o", out, "--name", "tiny")
    assert proc.returncode == 0, proc.stderr
    ds = hdf5.read(out)
    assert ds.name == "tiny" and ds.node_ids == ("a", "b", "c")
    d = shared_path("datasets", "hanyang-outdoor", "LOS", "Trajectory_A", "Case_1")
    out2 = tmp_path / "h.h5"
    proc = run_cli("import", "hanyang", d, "-o", out2, "--json")
    assert proc.returncode == 0, proc.stderr
    import json

    s = json.loads(proc.stdout)
    assert s["format"] == "trajectory" and s["anchors"] == 4 and s["ranges"] == hdf5.read(out2).n_ranges


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["nope", "x"], "unknown importer"),
        (["csv", "{tmp}/missing.csv"], "no such file"),
        (["csv", "{tmp}/bad.csv"], "missing column"),
    ],
)
def test_cli_import_errors_are_one_line(tmp_path, args, fragment):
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    proc = run_cli("import", *args, "-o", tmp_path / "out.h5")
    assert_one_line_error(proc, fragment)
    assert not (tmp_path / "out.h5").exists()
