"""The notebooks run from top to bottom (small sizes: JAXCAL_NOTEBOOK_QUICK=1), so they never rot.

Executed with nbclient on the `python3` kernel of the environment running the tests; outputs go to a
temporary folder (JAXCAL_NOTEBOOK_OUT), the notebooks on disk are not modified. The outputs stored in
them (full size, shown by the docs site) are written by `scripts/execute_notebooks.py`.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import ipykernel  # noqa: F401  (the test extra installs the runner; a missing one must fail, not skip)
import nbclient
import nbformat

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"


def _execute(name: str, tmp_path, monkeypatch):
    monkeypatch.setenv("JAXCAL_NOTEBOOK_QUICK", "1")
    monkeypatch.setenv("JAXCAL_NOTEBOOK_OUT", str(tmp_path))
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    client = nbclient.NotebookClient(
        nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}}
    )
    client.execute()
    return nb


def _text(nb) -> str:
    out = []
    for cell in nb.cells:
        for o in cell.get("outputs", []):
            out.append(o.get("text", ""))
            out.append(str(o.get("data", {}).get("text/plain", "")))
    return "\n".join(out)


def test_mesh_torgau_notebook(tmp_path, monkeypatch):
    nb = _execute("mesh_torgau.ipynb", tmp_path, monkeypatch)
    text = _text(nb)
    for label in ("cf/conf1", "cf/conf2", "pgp/conf1", "pgp/conf2"):
        assert re.search(rf"^{label} +\d+\.\d\d +\d+\.\d\d", text, re.M), label
    assert "parametric" not in text  # quick mode leaves the slow parametric filter out
    out = tmp_path / "mesh_torgau"
    assert (out / "index.html").is_file()
    for name in (
        "fig10_availability.png",
        "fig12b_ecdf_node_rmse.png",
        "fig06_posteriors_pgp_conf1.png",
    ):
        assert (out / name).stat().st_size > 5000
    images = sum("image/png" in o.get("data", {}) for c in nb.cells for o in c.get("outputs", []))
    assert images >= 10


def test_gp_trajectory_notebook(tmp_path, monkeypatch):
    nb = _execute("gp_trajectory.ipynb", tmp_path, monkeypatch)
    text = _text(nb)
    if "nothing to calibrate" in text:  # neither the shared recording nor the campus simulator exists
        assert not (tmp_path / "gp_trajectory").exists()
        return
    for method in ("gp", "nls", "ls"):
        assert re.search(rf"^{method} +mean anchor error \d+\.\d\d m", text, re.M), method
    assert (tmp_path / "gp_trajectory" / "anchors_trajectory.png").stat().st_size > 5000


def test_tuning_sweep_notebook(tmp_path, monkeypatch):
    nb = _execute("tuning_sweep.ipynb", tmp_path, monkeypatch)
    text = _text(nb)
    num = r"(-?\d+\.\d+)"
    for objective in ("truth", "evidence"):
        m = re.search(rf"^{objective} +{num} +{num} +{num} +{num} +{num} ", text, re.M)
        assert m, objective
        before, after, sigma_r, sigma_v, tau = map(float, m.groups())
        assert after <= before  # tune never hands back a worse point than its start
        assert sigma_r > 0 and sigma_v > 0 and 0 < tau < 1
    for label in ("start", "tuned: truth", "tuned: evidence"):
        assert re.search(rf"^{label} +{num} +{num} +{num} +{num} +{num}", text, re.M), label
    out = tmp_path / "tuning_sweep"
    numbers = json.loads((out / "report" / "report.json").read_text())
    (sw,) = numbers["sweeps"]
    assert len(sw["sigma_r_m"]) == 2 and len(sw["tau"]) == 2
    best = min(v for row in sw["values"] for v in row if v is not None)
    assert f"lowest RMSE {best:.2f} m" in text
    assert (out / "report" / "sweep_0.png").stat().st_size > 5000
    assert any("image/png" in o.get("data", {}) for c in nb.cells for o in c.get("outputs", []))
