"""pgp+batch: the PGP track is kept, the batch refinement never ends at a higher robust cost than batch alone."""

import numpy as np
import pytest

from jaxcal.data import MeshDataset
from jaxcal.errors import JaxcalError
from jaxcal.mesh import batch, hybrid
from jaxcal.mesh.frame import to_frame


def _scene(seed=3, n=6, k=30, outliers=True):
    rng = np.random.default_rng(seed)
    truth = rng.uniform(0, 20, (n, 2))
    d = np.linalg.norm(truth[:, None] - truth[None], axis=-1)
    r = d[None] + rng.normal(0, 0.05, (k, n, n))
    if outliers:
        r[rng.random((k, n, n)) < 0.03] += 20.0
    r[:, np.arange(n), np.arange(n)] = np.nan
    return MeshDataset(
        name="hyb", node_ids=[f"n{i}" for i in range(n)], time=np.arange(k) * 0.1, range=np.abs(r), truth=truth
    )


def test_split_params():
    p, b = hybrid.split_params({"pgp.cell_m": "0.25", "batch.loss": "huber", "sigma_r": "0.4"})
    assert p == {"cell_m": "0.25", "sigma_r": "0.4"} and b == {"loss": "huber", "sigma_r": "0.4"}
    with pytest.raises(JaxcalError, match="unknown parameter"):
        hybrid.split_params({"nonsense": 1})


def test_extra_starts_only_lower_the_cost():
    ds = _scene()
    plain = batch.solve(ds.range, (0, 1, 2), batch.BatchParams())
    truth_frame = to_frame(ds.truth, 0, 1, 2)
    with_truth = batch.solve(ds.range, (0, 1, 2), batch.BatchParams(), extra_starts=truth_frame[None])
    assert with_truth.cost <= plain.cost + 1e-9 * max(1.0, abs(plain.cost))


def test_hybrid_keeps_pgp_track_and_refines():
    ds = _scene()
    res = hybrid.calibrate(ds, {"pgp.cell_m": 0.5})
    assert res.method == "pgp+batch" and res.track_position is not None
    assert res.track_position.shape == (ds.n_epochs, ds.n_nodes, 2)
    assert any(k.startswith("pgp.") for k in res.params) and any(k.startswith("batch.") for k in res.params)
    truth = to_frame(ds.truth, 0, 1, 2)
    err = np.linalg.norm(res.position - truth, axis=1)
    assert np.all(err < 0.2), err  # 5 cm ranging noise, 3 % gross outliers: robust refinement lands close
    assert res.covariance.shape == (ds.n_nodes, 2, 2)


def _median_cost(range_m, x, p):
    """The batch solver's robust cost on the per-pair medians at positions x (any frame), offset 0."""
    import jax.numpy as jnp

    i, j, z, w = batch.observations(range_m, "median")
    obs = batch.Observations(*(jnp.asarray(a) for a in (i, j, z, w)))
    st = batch._State(jnp.asarray(x), jnp.zeros(()), jnp.zeros(x.shape[0]))
    return float(batch._cost(st, (obs, batch._Numbers.of(p))))


def test_hybrid_final_cost_not_above_pgp_and_error_not_worse():
    """pgp's final positions (the last epoch of the kept track) are one of the refinement's starts:
    the refined positions have a robust cost no higher than pgp's own, and (on this scene, 3 % gross
    outliers) no larger error against truth."""
    ds = _scene(seed=5)  # same shapes and static settings as the test above: its compilations are reused
    over = {"pgp.cell_m": 0.5, "batch.bias": "none", "batch.summary": "median"}
    res = hybrid.calibrate(ds, over)
    x_pgp = res.track_position[-1]  # pgp's final estimate
    p = batch.BatchParams(bias="none", summary="median")
    c_h, c_p = _median_cost(ds.range, res.position, p), _median_cost(ds.range, x_pgp, p)
    assert c_h <= c_p + 1e-9 * max(1.0, abs(c_p)), (c_h, c_p)
    truth = to_frame(ds.truth, 0, 1, 2)
    err_h = np.sqrt(np.mean(np.sum((res.position - truth) ** 2, axis=1)))
    err_p = np.sqrt(np.mean(np.sum((x_pgp - truth) ** 2, axis=1)))
    assert err_h <= err_p, (err_h, err_p)
    assert res.params["batch.bias"] == "none"
