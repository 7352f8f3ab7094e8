"""Shared fixtures. x64 is on so that reference comparisons are exact; fast paths that run in float32
state their dtype explicitly and their tests give loose tolerances with a comment."""

from __future__ import annotations

import atexit
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI (jaxcal.cli): before NumPy is imported

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from jaxcal import compile_cache
from jaxcal.executables import release_if_crowded

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
DATASETS = SHARED / "datasets"
PROTOCOLS = SHARED / "protocols"


def shared_path(*parts: str) -> Path:
    """A path under ../shared; skips the test cleanly when it is absent (a user's clone has no shared/)."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not available: {p}")
    return p


TEST_SEED = int(os.environ.get("JAXCAL_TEST_SEED", "12345"))


def _seed_list(text: str) -> list[int]:
    out = []
    for part in filter(None, text.split(",")):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b) + 1) if b else [int(a)])
    return out


def pytest_generate_tests(metafunc):
    # JAXCAL_TEST_SEEDS="0-19" runs every test that uses `rng` once per seed, in one process (compilations
    # are shared): the seed sweep that every assertion on random draws must pass.
    seeds = _seed_list(os.environ.get("JAXCAL_TEST_SEEDS", ""))
    if seeds and "rng_seed" in metafunc.fixturenames:
        metafunc.parametrize("rng_seed", seeds, ids=[f"seed{s}" for s in seeds])


@pytest.fixture
def rng_seed():
    return TEST_SEED


@pytest.fixture
def rng(rng_seed):
    """The tests' random generator. Its seed is JAXCAL_TEST_SEED (default 12345), so the suite can be
    run on other seeds (JAXCAL_TEST_SEEDS="0-19": every seed in one run): every assertion that depends on
    random draws must hold on any of them."""
    return np.random.default_rng(rng_seed)


@pytest.fixture(autouse=True)
def _release_executables_when_maps_run_high():
    """One pytest process compiles thousands of XLA programs; at the kernel's vm.max_map_count the
    next compile segfaulted (CI: test_tune, earlier test_sweep). See `jaxcal.executables`."""
    yield
    release_if_crowded()


# JAX's persistent compilation cache (`jaxcal.compile_cache`), one directory for the whole run, not the user's:
# the run leaves nothing behind. The process that imports this first (pytest itself; with xdist, the controller)
# makes the directory and deletes it at exit; its workers, the in-process command line (`cli.main`) and the CLI
# subprocesses (`run_cli`) inherit JAXCAL_TEST_XLA_CACHE / JAXCAL_CACHE_DIR and share it. Many tests build the
# same programs afresh (closures jitted per call, the same pipeline on the same shapes in several tests, a
# file's tests split over both workers); a program loaded from the cache is the same executable, so the same
# numbers (docs/benchmarks/index.md, sixteenth and seventeenth rounds). Entries are written atomically
# (`_atomic_cache_writes`), so a worker never reads one that another is still writing.
_XLA_CACHE_ENV = "JAXCAL_TEST_XLA_CACHE"
if not os.environ.get(_XLA_CACHE_ENV):
    os.environ[_XLA_CACHE_ENV] = tempfile.mkdtemp(prefix="jaxcal-test-xla-")
    atexit.register(shutil.rmtree, os.environ[_XLA_CACHE_ENV], True)
_XLA_CACHE = os.environ[_XLA_CACHE_ENV]
os.environ["JAXCAL_CACHE_DIR"] = _XLA_CACHE


def _atomic_cache_writes() -> None:
    """JAX's cache (without its optional `filelock` size limit) writes an entry in place, so another process can
    find the file before its last byte is there (JAX then warns and compiles again). Here an entry is written to
    a temporary name and renamed: readers see all of it or nothing. Left alone where JAX's internals differ."""
    try:
        from jax._src import lru_cache
    except ImportError:
        return
    cls, suffix = getattr(lru_cache, "LRUCache", None), getattr(lru_cache, "_CACHE_SUFFIX", None)
    if cls is None or suffix is None or not hasattr(cls, "put"):
        return
    original = cls.put

    def put(self, key: str, value: bytes) -> None:
        if getattr(self, "eviction_enabled", True):  # the locked path is safe as it is
            return original(self, key, value)
        path = Path(self.path) / f"{key}{suffix}"
        if not key or path.exists():
            return original(self, key, value)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        tmp.write_bytes(value)
        os.replace(tmp, path)

    cls.put = put


_atomic_cache_writes()
compile_cache.enable(_XLA_CACHE, min_compile_s=0.02)


def run_cli(*args: str, cwd: Path | None = None, timeout: float = 600, env: dict | None = None):
    """Run `python -m jaxcal.cli ARGS` in a subprocess; returns CompletedProcess (text)."""
    e = dict(os.environ)
    e.setdefault("JAX_PLATFORMS", "cpu")
    e.setdefault("JAXCAL_CACHE_DIR", _XLA_CACHE)
    e.pop("JAXCAL_DEBUG", None)
    if env:
        e.update(env)
    return subprocess.run(
        [sys.executable, "-m", "jaxcal.cli", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=timeout,
        env=e,
    )


def assert_one_line_error(proc, fragment: str | None = None, code: int = 2):
    """Bad input: the given exit status, exactly one line on stderr, no traceback."""
    assert proc.returncode == code, (proc.returncode, proc.stdout, proc.stderr)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    if fragment is not None:
        assert fragment.lower() in lines[0].lower(), lines[0]


def random_layout(rng: np.random.Generator, n: int, span: float, min_sep: float = 1.0):
    """Node positions uniform in a span x span square, redrawn until every pair is more than
    `min_sep` apart; returns (positions, (n, n) true distances)."""
    while True:
        pos = rng.uniform(0, span, (n, 2))
        d = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
        if d[np.triu_indices(n, 1)].min() > min_sep:
            return pos, d


def mesh_of(r: np.ndarray, truth: np.ndarray | None, **kw):
    """A test `MeshDataset` of (K, N, N) ranges (diagonal set to NaN) at 10 Hz."""
    from jaxcal.data import MeshDataset

    r = np.array(r, dtype=np.float64)
    k, n = r.shape[:2]
    r[:, np.arange(n), np.arange(n)] = np.nan
    return MeshDataset(
        name="t",
        node_ids=[f"n{i}" for i in range(n)],
        time=np.arange(k) * 0.1,
        range=r.astype(np.float32),
        truth=truth,
        **kw,
    )
