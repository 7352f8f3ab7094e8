import h5py
import numpy as np
import pytest

from jaxcal.data import Result
from jaxcal.errors import FormatError
from jaxcal.io import hdf5
from test_data import small_mesh, small_traj


def _eq(a, b):
    if a is None or b is None:
        return a is None and b is None
    return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)


def test_mesh_round_trip(tmp_path):
    ds = small_mesh(los=np.ones((4, 4)), configs={"conf1": (0, 1, 2), "conf2": (3, 2, 1)}, description="d")
    p = hdf5.write(tmp_path / "m.h5", ds)
    back = hdf5.read(p)
    for f in ("time", "range", "truth", "los", "fp_rssi"):
        assert _eq(getattr(ds, f), getattr(back, f)), f
    assert back.node_ids == ds.node_ids and back.name == ds.name
    assert dict(back.configs) == {"conf1": (0, 1, 2), "conf2": (3, 2, 1)}
    assert back.description == "d"
    with h5py.File(p) as f:  # the contract's dtypes and attributes
        assert f.attrs["jaxcal_format"] == "mesh" and int(f.attrs["jaxcal_version"]) == 1
        assert f["epochs/range"].dtype == np.float32 and f["links/los"].dtype == np.int8
        assert f["configs/conf2"].dtype == np.int64
        assert h5py.check_string_dtype(f["nodes/id"].dtype).encoding == "utf-8"


def test_trajectory_round_trip(tmp_path):
    q = np.tile([0.0, 0.0, 0.0, 1.0], (5, 1))
    ds = small_traj(pose_orientation=q, range_los=[1, 0, -1])
    back = hdf5.read(hdf5.write(tmp_path / "t.h5", ds))
    for f in (
        "anchor_truth",
        "lever_arm",
        "pose_time",
        "pose_position",
        "pose_orientation",
        "range_time",
        "range_anchor",
        "range_tag",
        "range",
        "range_los",
    ):
        assert _eq(getattr(ds, f), getattr(back, f)), f
    assert back.range_anchor.dtype == np.int32


def test_result_round_trip(tmp_path):
    res = Result(
        ids=["a", "b", "c"],
        position=[[0, 0], [1, 0], [np.nan, np.nan]],
        method="cf",
        dataset="x",
        frame="anchors:0,1,2",
        params={"sigma_r": 0.3, "top_k": 5},
        covariance=np.tile(np.eye(2), (3, 1, 1)),
        track_time=[0.0, 0.1],
        track_position=np.zeros((2, 3, 2)),
    )
    back = hdf5.read(hdf5.write(tmp_path / "r.h5", res))
    assert back.params == {"sigma_r": 0.3, "top_k": 5}
    assert _eq(back.position, res.position) and _eq(back.track_position, res.track_position)
    assert back.frame_anchors() == (0, 1, 2)
    with h5py.File(tmp_path / "r.h5") as f:
        assert f.attrs["software"].startswith("jaxcal ")


def _bad_file(path, **attrs):
    with h5py.File(path, "w") as f:
        for k, v in attrs.items():
            f.attrs[k] = v
    return path


@pytest.mark.parametrize(
    "attrs, msg",
    [
        ({}, "jaxcal_format"),
        ({"jaxcal_format": "banana", "jaxcal_version": 1}, "unknown jaxcal_format"),
        ({"jaxcal_format": "mesh", "jaxcal_version": 7}, "newer"),
        ({"jaxcal_format": "mesh", "jaxcal_version": 1}, "missing dataset"),
    ],
)
def test_bad_files_one_line(tmp_path, attrs, msg):
    p = _bad_file(tmp_path / "bad.h5", **attrs)
    with pytest.raises(FormatError, match=msg) as e:
        hdf5.read(p)
    assert "\n" not in str(e.value)


def test_inconsistent_shapes(tmp_path):
    p = hdf5.write(tmp_path / "m.h5", small_mesh())
    with h5py.File(p, "a") as f:
        del f["nodes/truth"]
        f["nodes/truth"] = np.zeros((7, 2))
    with pytest.raises(FormatError, match=r"truth: expected shape"):
        hdf5.read(p)


def test_garbage_and_missing(tmp_path):
    g = tmp_path / "g.h5"
    g.write_bytes(b"\x00garbage" * 100)
    with pytest.raises(FormatError, match="not a readable HDF5"):
        hdf5.read(g)
    with pytest.raises(FormatError, match="no such file"):
        hdf5.read(tmp_path / "nope.h5")


def test_write_is_atomic(tmp_path):
    p = hdf5.write(tmp_path / "m.h5", small_mesh())
    before = p.read_bytes()
    with pytest.raises(TypeError):
        hdf5.write(p, object())
    assert p.read_bytes() == before
    assert [x.name for x in tmp_path.iterdir()] == ["m.h5"]


def test_writer_refuses_a_covariance_that_is_not_psd(tmp_path):
    base = dict(ids=["a", "b"], position=[[0, 0], [1, 0]], method="batch", dataset="x", frame="anchors:0,1,2")
    bad = np.stack([np.eye(2), np.diag([1.0, -1e11])])
    with pytest.raises(FormatError, match="'b'.*positive semi-definite"):
        hdf5.write(tmp_path / "r.h5", Result(covariance=bad, **base))
    asym = np.stack([np.eye(2), np.array([[1.0, 0.5], [0.0, 1.0]])])
    with pytest.raises(FormatError, match="symmetric"):
        hdf5.write(tmp_path / "r.h5", Result(covariance=asym, **base))
    assert not (tmp_path / "r.h5").exists()
    # float32 rounding of a symmetric block (the command line computes in float32) is not refused
    near = np.stack([np.eye(2), np.array([[0.25764145, 0.23082632], [0.2308263, 0.59473445]])])
    hdf5.write(tmp_path / "r.h5", Result(covariance=near, **base))
    # NaN blocks (no estimate) and a NaN coordinate (unobservable axis) are not refused
    ok = np.stack([np.full((2, 2), np.nan), np.array([[1.0, np.nan], [np.nan, np.nan]])])
    hdf5.write(tmp_path / "r.h5", Result(covariance=ok, **base))
