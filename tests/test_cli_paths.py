"""Output paths of the command line (issue #25, items 1, 3, 4, 6): an input is never overwritten, a bad
output path is refused before any work with the user's path and the true reason, files get the umask's
permissions, overwriting says so; `--config` and `--list-params` are shared by the commands."""

from __future__ import annotations

import errno
import json
import os
import stat
import subprocess
import sys

import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli
from jaxcal.io import hdf5
from test_data import small_mesh


@pytest.fixture
def mesh(tmp_path):
    return hdf5.write(tmp_path / "rec.h5", small_mesh(configs={"conf1": (0, 1, 2)}))


def _no_temporaries(folder):
    left = [p.name for p in folder.iterdir() if p.name.endswith(".tmp") or ".jaxcal-probe." in p.name]
    assert not left, left


def test_output_that_is_an_input_is_refused(mesh, tmp_path, monkeypatch):
    before = mesh.read_bytes()
    (tmp_path / "link.h5").symlink_to(mesh)
    os.link(mesh, tmp_path / "hard.h5")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sub").mkdir()
    for out in ("./sub/../rec.h5", "link.h5", "hard.h5"):
        p = run_cli("calibrate", mesh, "--method", "cf", "-o", out, cwd=tmp_path)
        assert_one_line_error(p, "is an input of this run")
        assert out in p.stderr  # the user's path, as given
    p = run_cli("tune", mesh, "-o", "link.h5", cwd=tmp_path)
    assert_one_line_error(p, "is an input of this run")
    p = run_cli("import", "csv", "rec.h5", "-o", "hard.h5", cwd=tmp_path)
    assert_one_line_error(p, "is an input of this run")
    assert mesh.read_bytes() == before and (tmp_path / "link.h5").is_symlink()
    _no_temporaries(tmp_path)


def test_overwrite_is_allowed_and_said_and_files_get_umask_permissions(mesh, tmp_path):
    out = tmp_path / "r.h5"
    p = run_cli("calibrate", mesh, "--method", "cf", "-o", out)
    assert p.returncode == 0, p.stderr
    assert "overwrote" not in p.stdout
    assert stat.S_IMODE(out.stat().st_mode) == 0o666 & ~_umask()
    os.chmod(out, 0o600)
    p = run_cli("calibrate", mesh, "--method", "cf", "-o", out, "--json")
    assert json.loads(p.stdout)["overwrote"] is True
    p = run_cli("calibrate", mesh, "--method", "cf", "-o", out)
    assert p.returncode == 0 and f"(overwrote {out})" in p.stdout
    assert stat.S_IMODE(out.stat().st_mode) == 0o666 & ~_umask()
    # another umask: the files follow it (simulate writes through the same helper)
    q = tmp_path / "s.h5"
    p = subprocess.run(
        [
            "sh",
            "-c",
            f'umask 077; exec "{sys.executable}" -m jaxcal.cli simulate mesh --scenario small -o "{q}" --quiet',
        ],
        capture_output=True,
        text=True,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
    )
    assert p.returncode == 0 and p.stdout == "", (p.stdout, p.stderr)
    assert stat.S_IMODE(q.stat().st_mode) == 0o600
    _no_temporaries(tmp_path)


def _umask() -> int:
    m = os.umask(0o022)
    os.umask(m)
    return m


def test_bad_output_paths_name_the_path_and_the_reason(mesh, tmp_path):
    cases = [
        (tmp_path / "missing" / "x.h5", "folder"),  # missing folder
        (tmp_path, "is a folder"),
        ("/proc/x.h5", "cannot write in /proc"),
    ]
    for out, reason in cases:
        p = run_cli("calibrate", mesh, "--method", "pgp", "-o", out)
        assert_one_line_error(p, reason)
        assert str(out) in p.stderr and ".tmp" not in p.stderr
    p = run_cli("simulate", "mesh", "-o", tmp_path / "nope" / "x.h5")
    assert_one_line_error(p, "does not exist")
    p = run_cli("demo", "-o", mesh)
    assert_one_line_error(p, "not a folder")
    p = run_cli("report", mesh, "--truth", tmp_path / "missing.h5", "-o", tmp_path / "rep")
    assert_one_line_error(p, "no such file")
    assert not (tmp_path / "rep").exists()


@pytest.mark.parametrize(
    "err, reason",
    [(errno.EROFS, "read-only file system"), (errno.EACCES, "permission denied"), (errno.ENOSPC, "no space")],
)
def test_probe_reasons(tmp_path, monkeypatch, err, reason):
    """The reason comes from the errno of a real create in the folder (root passes permission checks, so
    the errno is injected here; /proc above is the real thing)."""
    import tempfile

    from jaxcal.commands._common import check_output_path
    from jaxcal.errors import JaxcalError

    def refuse(*a, **k):
        raise OSError(err, os.strerror(err))

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(JaxcalError, match=reason) as e:
        check_output_path(tmp_path / "x.h5")
    assert str(tmp_path / "x.h5") in str(e.value)


def test_output_checked_before_the_computation(mesh, tmp_path):
    """A long method with a bad output fails at once, before any JAX computation."""
    # with no usable JAX backend, any computation would fail with another message: the path error is first
    env = {"JAX_PLATFORMS": "no-such-backend"}
    for args in (["calibrate", mesh, "--method", "pgp"], ["tune", mesh]):
        p = run_cli(*args, "-o", tmp_path / "missing" / "x.h5", env=env)
        assert_one_line_error(p, "folder")
        assert "backend" not in p.stderr


def test_config_name_or_node_ids(mesh, tmp_path):
    a = run_cli("calibrate", mesh, "--method", "cf", "-o", tmp_path / "a.h5", "--config", "conf1")
    b = run_cli("calibrate", mesh, "--method", "cf", "-o", tmp_path / "b.h5", "--config", "n0,n1,n2")
    assert a.returncode == 0 and b.returncode == 0, (a.stderr, b.stderr)
    ra, rb = hdf5.read(tmp_path / "a.h5"), hdf5.read(tmp_path / "b.h5")
    assert ra.frame == rb.frame == "anchors:0,1,2"
    np.testing.assert_allclose(ra.position, rb.position)
    c = run_cli("calibrate", mesh, "--method", "cf", "-o", tmp_path / "c.h5", "--config", "n2,n0,n3")
    assert c.returncode == 0 and hdf5.read(tmp_path / "c.h5").frame == "anchors:2,0,3"
    assert_one_line_error(
        run_cli("calibrate", mesh, "--method", "cf", "-o", tmp_path / "d.h5", "--config", "n0,n1,zz"),
        "unknown node id(s) zz",
    )
    assert_one_line_error(
        run_cli("tune", mesh, "-o", tmp_path / "p.json", "--config", "n0,n0,n1"), "three distinct node ids"
    )
    assert not (tmp_path / "d.h5").exists()


def test_list_params_is_generated_from_the_params_classes():
    import dataclasses

    from jaxcal.methods import METHOD_PARAMS, param_defaults
    from jaxcal.params import describe

    for method in METHOD_PARAMS:
        for d in param_defaults(method):
            rows = describe(d)
            assert [r["name"] for r in rows] == [f.name for f in dataclasses.fields(d)]
            assert all(r["meaning"] for r in rows), (method, [r["name"] for r in rows if not r["meaning"]])
    p = run_cli("calibrate", "--method", "pgp", "--list-params")
    assert p.returncode == 0, p.stderr
    line = next(x for x in p.stdout.splitlines() if x.split()[:1] == ["sigma_r"])
    assert "0.3 [m]" in line and "ranging standard deviation" in line
    j = json.loads(run_cli("calibrate", "--method", "pgp+batch", "--list-params", "--json").stdout)
    names = {r["name"] for r in j["params"]}
    assert {"pgp.sigma_r", "batch.loss"} <= names
    assert_one_line_error(run_cli("calibrate", "--method", "nosuch", "--list-params"), "unknown method")


def test_every_command_takes_json_and_quiet():
    from jaxcal.cli import COMMANDS, build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for name in COMMANDS:
        flags = {o for a in sub.choices[name]._actions for o in a.option_strings}
        assert {"--json", "--quiet"} <= flags, name


def test_resolve_config_in_process():
    from jaxcal.commands._common import parse_config, resolve_config
    from jaxcal.errors import JaxcalError

    ds = small_mesh(configs={"conf1": (0, 1, 2)})
    assert resolve_config(ds, None) == (ds, None)
    assert resolve_config(ds, "conf1")[1] == "conf1"
    d2, name = resolve_config(ds, " n3, n1 ,n0")
    assert name == "n3,n1,n0" and d2.config(name) == (3, 1, 0) and dict(d2.configs)["conf1"] == (0, 1, 2)
    assert resolve_config(ds, "2,0,1")[0].config("2,0,1") == (2, 0, 1)  # indices when they are not ids
    assert parse_config("a,b,c") == ("a", "b", "c")
    for bad, msg in (
        ("nosuch", "known: conf1"),
        ("n0,n1", "three distinct"),
        ("n0,n1,n1", "three distinct"),
        ("", "empty"),
        ("n0,n1,x9", "unknown node id"),
    ):
        with pytest.raises(JaxcalError, match=msg):
            resolve_config(ds, bad)
