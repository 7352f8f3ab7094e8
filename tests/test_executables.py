"""jaxcal.executables: dropping JAX's caches frees the executables' memory maps, results unchanged."""

import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.executables import map_count, release_if_crowded


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="memory maps are counted in /proc")
def test_release_frees_the_maps_of_compiled_programs_and_results_stay():
    release_if_crowded(limit=0)
    before = map_count()
    fns = [jax.jit(lambda x, i=i: jnp.sin(x) * i) for i in range(24)]
    first = [np.asarray(f(jnp.arange(i + 1.0))) for i, f in enumerate(fns)]
    grown = map_count()
    assert grown > before + 24  # each live executable holds memory maps of its own
    assert not release_if_crowded(limit=grown + 1_000)  # below the limit: nothing dropped
    assert release_if_crowded(limit=0)
    assert map_count() < grown - 24
    again = [np.asarray(f(jnp.arange(i + 1.0))) for i, f in enumerate(fns)]  # compiled anew
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a, b)


def test_calibrate_drops_the_caches_of_a_crowded_process_first(monkeypatch):
    """A loop of `calibrate` calls over datasets of new shapes never reaches the kernel's map limit: every call
    first drops JAX's caches when the process holds too many maps (here: pretended), and leaves them otherwise."""
    import jaxcal.executables as ex
    from jaxcal.methods import calibrate
    from jaxcal.sim.trajectory import simulate

    ds = simulate("small", seed=0)
    f = jax.jit(lambda x: x + 1.0)
    f(jnp.ones(3))
    assert f._cache_size() == 1
    calibrate(ds, "ls")  # not crowded: the user's compiled programs stay
    assert f._cache_size() == 1 or ex.map_count() > ex.MAPS_LIMIT
    monkeypatch.setattr(ex, "map_count", lambda: ex.MAPS_LIMIT + 1)
    res = calibrate(ds, "ls")
    assert f._cache_size() == 0
    assert np.isfinite(res.position[:, :2]).all()
