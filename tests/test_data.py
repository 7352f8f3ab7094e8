import numpy as np
import pytest

from jaxcal.data import MeshDataset, Result, TrajectoryDataset
from jaxcal.errors import DataError


def small_mesh(k=4, n=4, **kw):
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 10, (n, 2))
    d = np.linalg.norm(truth[:, None] - truth[None], axis=-1)
    r = np.repeat(d[None], k, axis=0).astype(np.float32)
    for e in range(k):
        np.fill_diagonal(r[e], np.nan)
    args = dict(name="t", node_ids=[f"n{i}" for i in range(n)], time=np.arange(k) * 0.1, range=r, truth=truth)
    args.update(kw)
    return MeshDataset(**args)


def small_traj(**kw):
    args = dict(
        name="tr",
        anchor_ids=["A", "B"],
        tag_ids=["T"],
        lever_arm=np.zeros((1, 3)),
        pose_time=np.arange(5.0),
        pose_position=np.zeros((5, 3)),
        range_time=np.array([0.5, 1.0, 2.0]),
        range_anchor=[0, 1, 0],
        range_tag=[0, 0, 0],
        range=[1.0, 2.0, 3.0],
        anchor_truth=np.ones((2, 3)),
    )
    args.update(kw)
    return TrajectoryDataset(**args)


def test_mesh_valid_and_dtypes():
    ds = small_mesh()
    assert ds.range.dtype == np.float32 and ds.time.dtype == np.float64
    assert ds.n_nodes == 4 and ds.n_epochs == 4
    assert ds.config(None) == (0, 1, 2)


@pytest.mark.parametrize(
    "change, field",
    [
        (dict(range=np.zeros((4, 4, 3))), "range"),
        (dict(time=np.array([0.0, 0.2, 0.1, 0.3])), "time"),
        (dict(node_ids=["a", "b", "a", "c"]), "node_ids"),
        (dict(truth=np.zeros((4, 4))), "truth"),
        (dict(los=np.full((4, 4), 5)), "los"),
        (dict(configs={"c": (0, 0, 1)}), "configs"),
    ],
)
def test_mesh_errors_name_the_field(change, field):
    with pytest.raises(DataError, match=rf"MeshDataset\.{field}"):
        small_mesh(**change)


def test_mesh_negative_range_rejected():
    ds = small_mesh()
    r = ds.range.copy()
    r[1, 0, 1] = -0.5
    with pytest.raises(DataError, match=r"range: negative value"):
        small_mesh(range=r)


def test_mesh_nan_is_missing_not_error():
    ds = small_mesh()
    r = ds.range.copy()
    r[:, 0, 1] = np.nan
    assert np.isnan(small_mesh(range=r).range[:, 0, 1]).all()


def test_unknown_config_names_known():
    ds = small_mesh(configs={"conf1": (0, 1, 2)})
    with pytest.raises(DataError, match="conf1"):
        ds.config("conf9")


@pytest.mark.parametrize(
    "change, field",
    [
        (dict(pose_time=np.array([0.0, 1.0, 1.0, 2.0, 3.0])), "pose_time"),
        (dict(range_anchor=[0, 2, 0]), "range_anchor"),
        (dict(range=[1.0, -2.0, 3.0]), "range"),
        (dict(pose_orientation=np.zeros((5, 4))), "pose_orientation"),
        (dict(lever_arm=np.zeros((2, 3))), "lever_arm"),
        (dict(anchor_ids=["A", "A"]), "anchor_ids"),
    ],
)
def test_trajectory_errors_name_the_field(change, field):
    with pytest.raises(DataError, match=rf"TrajectoryDataset\.{field}"):
        small_traj(**change)


def test_result_checks():
    Result(ids=["a", "b", "c"], position=np.zeros((3, 2)), method="cf", dataset="x", frame="anchors:0,1,2")
    with pytest.raises(DataError, match=r"Result\.track"):
        Result(ids=["a"], position=np.zeros((1, 2)), method="m", dataset="x", frame="world", track_time=[0.0])
    with pytest.raises(DataError, match=r"Result\.frame"):
        Result(ids=["a"], position=np.zeros((1, 2)), method="m", dataset="x", frame="nowhere")


def test_is_pytree():
    import jax

    ds = small_mesh()
    leaves = jax.tree_util.tree_leaves(ds)
    assert any(leaf is ds.range for leaf in leaves)
    doubled = jax.tree_util.tree_map(lambda x: x * 2, ds)
    assert np.allclose(doubled.time, ds.time * 2)
