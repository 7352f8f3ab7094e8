"""Execute the notebooks in notebooks/ in place, storing their outputs and figures (full size).

    .venv/bin/python scripts/execute_notebooks.py [NAME.ipynb ...]

The stored outputs are what the docs site shows (mkdocs-jupyter with `execute: false`). The test
(tests/test_notebooks.py) re-executes them in quick mode and never writes them. Figures are the
report's PNGs, shown through IPython.display.Image.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import nbclient
import nbformat

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"


def main(names: list[str]) -> int:
    os.environ.pop("JAXCAL_NOTEBOOK_QUICK", None)
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    paths = [NOTEBOOKS / n for n in names] if names else sorted(NOTEBOOKS.glob("*.ipynb"))
    with tempfile.TemporaryDirectory(prefix="jaxcal-nb-") as out:
        os.environ["JAXCAL_NOTEBOOK_OUT"] = out
        for path in paths:
            t0 = time.perf_counter()
            nb = nbformat.read(path, as_version=4)
            client = nbclient.NotebookClient(
                nb,
                timeout=3600,
                kernel_name="python3",
                resources={"metadata": {"path": str(NOTEBOOKS)}},
            )
            client.execute()
            nbformat.write(nb, path)
            size = path.stat().st_size
            print(f"{path.name}: {time.perf_counter() - t0:.0f} s, {size / 1e6:.2f} MB", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
