"""Helpers shared by the importers: file checks, csv tables with line numbers, numeric cells, counters."""

from __future__ import annotations

import csv
import os
from collections import Counter
from collections.abc import Iterator, Sequence
from pathlib import Path

from jaxcal.errors import JaxcalError


class BadCell(ValueError):
    """A cell that cannot be used; carries the column name for the error message."""

    def __init__(self, column: str, value: str, why: str = "not a number"):
        super().__init__(f"column {column!r}: {why} {value!r}")
        self.column = column


def existing_file(path: str | os.PathLike, what: str = "file") -> Path:
    """`path` as a Path, or a one-line JaxcalError when it is missing or a folder."""
    p = Path(path)
    if not p.exists():
        raise JaxcalError(f"{p}: no such {what}")
    if p.is_dir():
        raise JaxcalError(f"{p}: is a folder, expected a {what}")
    if p.stat().st_size == 0:
        raise JaxcalError(f"{p}: empty file")
    return p


def existing_dir(path: str | os.PathLike) -> Path:
    """`path` as a Path, or a one-line JaxcalError when it is missing or not a folder."""
    p = Path(path)
    if not p.exists():
        raise JaxcalError(f"{p}: no such folder")
    if not p.is_dir():
        raise JaxcalError(f"{p}: is a file, expected a folder")
    return p


def num(value: str, column: str) -> float:
    """A numeric cell as float; 'nan' and empty cells are NaN (missing); anything else raises BadCell."""
    v = value.strip()
    if v == "" or v.lower() == "nan":
        return float("nan")
    try:
        x = float(v)
    except ValueError:
        raise BadCell(column, value) from None
    if x != x or x in (float("inf"), float("-inf")):
        raise BadCell(column, value, "not a finite number")
    return x


def finite(value: str, column: str) -> float:
    """A numeric cell that must be present and finite (times, coordinates)."""
    x = num(value, column)
    if x != x:
        raise BadCell(column, value, "missing value")
    return x


def csv_rows(path: Path, required: Sequence[str], header: bool = True) -> tuple[list[str], Iterator]:
    """Open a csv table; returns (header, iterator of (line_number, row)).

    With `header`, the first line must contain every name in `required` (an error names the missing one).
    Raises JaxcalError for an empty or undecodable file.
    """
    try:
        f = open(path, newline="", encoding="utf-8-sig")
    except OSError as e:
        raise JaxcalError(f"{path}: cannot open ({e.strerror})") from None
    reader = csv.reader(f)
    cols: list[str] = []
    try:
        if header:
            try:
                cols = [c.strip() for c in next(reader)]
            except StopIteration:
                f.close()
                raise JaxcalError(f"{path}: empty file") from None
            missing = [c for c in required if c not in cols]
            if missing:
                f.close()
                shown = ",".join(cols[:10]) + (",..." if len(cols) > 10 else "")
                raise JaxcalError(f"{path}:1: missing column {missing[0]!r} (header is {shown!r})")
    except UnicodeDecodeError:
        f.close()
        raise JaxcalError(f"{path}: not a text csv file (cannot decode as UTF-8)") from None

    def rows():
        try:
            for row in reader:
                if not row or all(not c.strip() for c in row):
                    continue
                yield reader.line_num, row
        except (UnicodeDecodeError, csv.Error) as e:
            raise JaxcalError(f"{path}:{reader.line_num}: unreadable csv ({_short(e)})") from None
        finally:
            f.close()

    return cols, rows()


def _short(e: BaseException) -> str:
    return " ".join(str(e).split())[:120]


class Skipped:
    """Counts skipped rows by reason and remembers the first offence (for the all-bad error)."""

    def __init__(self, path: Path):
        self.path = path
        self.counts: Counter[str] = Counter()
        self.first: str | None = None

    def add(self, reason: str, line: int, detail: str = "") -> None:
        self.counts[reason] += 1
        if self.first is None:
            self.first = f"{self.path}:{line}: {detail or reason}"

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def fail_if_nothing(self, n_good: int) -> None:
        """Raise when the file gave no usable row at all."""
        if n_good == 0:
            if self.first is not None:
                raise JaxcalError(f"{self.first} (no usable row in the file)")
            raise JaxcalError(f"{self.path}: no data rows")

    def describe(self) -> str:
        """E.g. 'A3.csv: skipped 2 rows (1 non-numeric, 1 negative range)'; '' when none."""
        if not self.total:
            return ""
        parts = ", ".join(f"{n} {r}" for r, n in sorted(self.counts.items()))
        return f"{self.path.name}: skipped {self.total} row(s) ({parts})"


def join_notes(*notes: str) -> str:
    return "; ".join(n for n in notes if n)
