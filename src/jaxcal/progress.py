"""Progress bars for long commands: tqdm on a terminal, nothing otherwise.

Core functions never print; a long one accepts an optional callback `progress(n_done)` that it calls
with the units completed since the last call (epochs of a scan run in segments, runs of a sweep, steps
of a tuner). Commands create the bar and hand its `update` down:

    with progress_bar(total=n_epochs, desc="pgp", unit="epoch", enabled=not args.quiet) as bar:
        result = calibrate(ds, "pgp", progress=bar.update)

The bar shows on stderr only when `enabled` and stderr is a terminal (so `--json`, `--quiet`, pipes and
CI stay clean); `JAXCAL_PROGRESS=1` forces it on, `JAXCAL_PROGRESS=0` off (tests use both).
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable, Iterator
from typing import Protocol

ProgressCallback = Callable[[int], None]


class Bar(Protocol):
    def update(self, n: int = 1) -> None: ...

    def set_postfix_str(self, s: str) -> None: ...


class _Silent:
    """The bar when progress is off: the same methods, doing nothing."""

    def update(self, n: int = 1) -> None:
        pass

    def set_postfix_str(self, s: str) -> None:
        pass


def wanted(enabled: bool = True) -> bool:
    """Whether a bar would be shown: `enabled`, stderr a terminal, unless JAXCAL_PROGRESS says otherwise."""
    forced = os.environ.get("JAXCAL_PROGRESS", "")
    if forced == "0":
        return False
    if forced == "1":
        return enabled
    return enabled and sys.stderr.isatty()


@contextlib.contextmanager
def progress_bar(total: int | None, desc: str, unit: str = "it", enabled: bool = True) -> Iterator[Bar]:
    """A tqdm bar (count, rate, ETA) on stderr, or a silent stand-in; closed on exit, also on Ctrl-C."""
    if not wanted(enabled):
        yield _Silent()
        return
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True, leave=False)
    try:
        yield bar
    finally:
        bar.close()
