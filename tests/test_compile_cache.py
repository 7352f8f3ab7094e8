"""The command line's persistent compilation cache: on by default, off by JAXCAL_CACHE_DIR=off, the
same results from a cached program, and no harm from an unusable directory."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from conftest import run_cli
from jaxcal.io import hdf5

PROBE = (
    "from jaxcal import compile_cache as c; import jax, jax.numpy as jnp; "
    "d = c.enable(min_compile_s=0); print(d); "
    "print(float(jax.jit(lambda x: jnp.sin(x) * 3 + 1)(jnp.arange(5.0)).sum()))"
)


def probe(env_value, tmp_path):
    env = {"JAXCAL_CACHE_DIR": str(env_value), "JAX_PLATFORMS": "cpu", "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_cache_stores_programs_and_is_off_on_request(tmp_path):
    where = tmp_path / "xla"
    first = probe(where, tmp_path)
    assert first[0] == str(where) and any(where.iterdir())  # the program was stored
    second = probe(where, tmp_path)
    assert second == first  # loaded from the cache: the same value
    off = tmp_path / "off"
    assert probe("off", tmp_path)[0] == "None"
    assert not off.exists()
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    assert probe(blocked / "xla", tmp_path)[0] == "None"  # unusable: silently off


def test_calibrate_gives_the_same_result_from_cached_programs(tmp_path):
    f = tmp_path / "d.h5"
    assert run_cli("simulate", "mesh", "--scenario", "small", "--seed", "3", "-o", f).returncode == 0
    cache = {"JAXCAL_CACHE_DIR": str(tmp_path / "xla")}
    outs = []
    for k in range(2):
        out = tmp_path / f"r{k}.h5"
        proc = run_cli("calibrate", f, "--method", "pgp", "-o", out, env=cache)
        assert proc.returncode == 0, proc.stderr
        outs.append(hdf5.read(out))
    np.testing.assert_array_equal(outs[0].position, outs[1].position)
    assert any((tmp_path / "xla").iterdir())
