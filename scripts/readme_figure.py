"""Make the README's figure: PGP and CF against the truth on the embedded `data/torgau.h5`.

    .venv/bin/python scripts/readme_figure.py        # writes docs/images/quickstart-torgau.png

The same as the README's quickstart (`jaxcal calibrate ... --method pgp|cf --config conf1`, then
`jaxcal report ... --truth data/torgau.h5`): the figure is the report's final-positions panel
(`positions_conf1.png`, 95 % ellipses from the results' covariances), at a modest resolution.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "images" / "quickstart-torgau.png"


def main() -> int:
    from jaxcal.io import hdf5
    from jaxcal.methods import calibrate
    from jaxcal.metrics import evaluate
    from jaxcal.report import write_report

    ds = hdf5.read(ROOT / "data" / "torgau.h5")
    results = [calibrate(ds, m, config="conf1") for m in ("pgp", "cf")]
    for r in results:
        ev = evaluate(r, ds)
        print(f"{r.method:4} conf1: RMSE {ev['rmse_m']:.2f} m, final {ev['final_rmse_m']:.2f} m")
    with tempfile.TemporaryDirectory() as tmp:
        write_report(results, ds, tmp, posteriors="none", dpi=80)
        OUT.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(Path(tmp) / "positions_conf1.png", OUT)
    print(f"wrote {OUT.relative_to(ROOT)} ({OUT.stat().st_size / 1e3:.0f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
