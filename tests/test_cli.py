"""The command line in a subprocess: output, and one-line errors with exit status 2 on bad input."""

import json

import h5py
import pytest

from conftest import assert_one_line_error, run_cli
from jaxcal.errors import InputError
from jaxcal.io import hdf5
from test_data import small_mesh, small_traj


def test_help_and_version():
    p = run_cli("--help")
    assert p.returncode == 0 and "calibrate" in p.stdout
    v = run_cli("--version")
    assert v.returncode == 0 and v.stdout.startswith("jaxcal ")


def test_info_and_validate(tmp_path):
    m = hdf5.write(tmp_path / "m.h5", small_mesh(configs={"conf1": (0, 1, 2)}))
    t = hdf5.write(tmp_path / "t.h5", small_traj())
    p = run_cli("info", m)
    assert p.returncode == 0 and "nodes: 4" in p.stdout and "epochs: 4" in p.stdout
    j = json.loads(run_cli("info", m, "--json").stdout)
    assert j["format"] == "mesh" and j["epochs"] == 4 and j["truth"] is True
    assert abs(j["availability"]["n0"] - 1.0) < 1e-12
    jt = json.loads(run_cli("info", t, "--json").stdout)
    assert jt["format"] == "trajectory" and jt["ranges"] == 3 and jt["ranges_per_anchor"] == {"A": 2, "B": 1}
    v = run_cli("validate", t)
    assert v.returncode == 0 and "valid jaxcal trajectory" in v.stdout


def test_bad_input_one_line(tmp_path):
    assert_one_line_error(run_cli("info", tmp_path / "missing.h5"), "no such file")
    garbage = tmp_path / "garbage.h5"
    garbage.write_bytes(b"not an hdf5 file at all")
    assert_one_line_error(run_cli("validate", garbage), "not a readable HDF5")
    wrong = tmp_path / "wrong.h5"
    with h5py.File(wrong, "w") as f:
        f.attrs["jaxcal_format"] = "spreadsheet"
        f.attrs["jaxcal_version"] = 1
    assert_one_line_error(run_cli("info", wrong), "jaxcal_format")
    assert_one_line_error(run_cli("nosuchcommand"), "invalid choice")
    m = hdf5.write(tmp_path / "m.h5", small_mesh())
    assert_one_line_error(run_cli("calibrate", m, "--method", "nosuch", "-o", tmp_path / "r.h5"), "unknown method")
    assert_one_line_error(
        run_cli("calibrate", m, "--method", "cf", "-o", tmp_path / "r.h5", "--set", "oops"), "KEY=VALUE"
    )


@pytest.mark.parametrize(
    "exc, code, head",
    [
        (InputError("top_k must be in [1, 5], got 9"), 2, "jaxcal: error: top_k must be"),
        (ValueError("operands could not be broadcast"), 1, "jaxcal: internal error: ValueError: operands"),
        (KeyboardInterrupt(), 130, "jaxcal: interrupted"),
    ],
)
def test_user_errors_are_told_from_internal_ones(monkeypatch, capsys, exc, code, head):
    """A user-fixable `InputError` (a `ValueError` too) exits 2; a plain ValueError from deep inside is an
    internal error (exit 1), never blamed on the user; Ctrl-C stays 130. One line each."""
    from jaxcal import cli
    from jaxcal.commands import info

    def fail(args):
        raise exc

    monkeypatch.setattr(info, "run", fail)
    monkeypatch.delenv("JAXCAL_DEBUG", raising=False)
    assert cli.main(["info", "x.h5"]) == code
    err = capsys.readouterr().err
    assert err.startswith(head) and err.count("\n") == 1
