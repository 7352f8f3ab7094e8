"""Method parameters: typed defaults, overrides from `--set KEY=VALUE` and JSON files.

Every method keeps its parameters in one `eqx.Module` of defaults. `with_overrides` returns a copy with
user values cast to the type of each default; an unknown key is an error naming the known ones.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, TypeVar

from jaxcal.errors import JaxcalError

T = TypeVar("T")

__all__ = ["parse_set", "with_overrides", "as_dict", "load_params_json"]


def parse_set(items: Iterable[str] | None) -> dict[str, str]:
    """['a=1', 'b=x'] -> {'a': '1', 'b': 'x'}; a malformed item is an error."""
    out: dict[str, str] = {}
    for item in items or ():
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise JaxcalError(f"--set expects KEY=VALUE, got {item!r}")
        out[key.strip()] = value.strip()
    return out


def load_params_json(path: str | Path) -> dict[str, Any]:
    """Parameters from a JSON object file (e.g. written by `jaxcal tune`); a `params` key is unwrapped."""
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise JaxcalError(f"{p}: no such file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise JaxcalError(f"{p}: not a JSON file ({e})") from None
    if isinstance(data, dict) and isinstance(data.get("params"), dict):
        data = data["params"]
    if not isinstance(data, dict):
        raise JaxcalError(f"{p}: expected a JSON object of parameters")
    return data


def _cast(key: str, default: Any, value: Any) -> Any:
    if getattr(default, "ndim", None) == 0 and hasattr(default, "item"):
        default = default.item()  # a 0-d array default (an eqx.Module field with an array converter)
    if isinstance(value, str):
        text = value
        if isinstance(default, bool):
            low = text.lower()
            if low in ("1", "true", "yes", "on"):
                return True
            if low in ("0", "false", "no", "off"):
                return False
            raise JaxcalError(f"parameter {key}: expected true/false, got {text!r}")
        if isinstance(default, int) and not isinstance(default, bool):
            try:
                return int(text)
            except ValueError:
                raise JaxcalError(f"parameter {key}: expected an integer, got {text!r}") from None
        if isinstance(default, float) or default is None:
            try:
                v = float(text)
            except ValueError:
                if default is None:
                    return text
                raise JaxcalError(f"parameter {key}: expected a number, got {text!r}") from None
            if math.isnan(v):
                raise JaxcalError(f"parameter {key}: NaN is not a valid value")
            return v
        return text
    if isinstance(default, bool):
        return bool(value)
    if isinstance(default, int) and isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(default, float) and isinstance(value, (int, float)):
        return float(value)
    return value


def with_overrides(defaults: T, overrides: Mapping[str, Any] | None) -> T:
    """Copy of the dataclass / eqx.Module `defaults` with `overrides` applied and cast."""
    if not overrides:
        return defaults
    fields = {f.name: getattr(defaults, f.name) for f in dataclasses.fields(defaults)}  # type: ignore[arg-type]
    changes = {}
    for key, value in overrides.items():
        if key not in fields:
            known = ", ".join(sorted(fields))
            raise JaxcalError(f"unknown parameter {key!r} (known: {known})")
        changes[key] = _cast(key, fields[key], value)
    return dataclasses.replace(defaults, **changes)  # type: ignore[type-var]


def as_dict(params: Any) -> dict[str, Any]:
    """Parameters as a plain dict of JSON-able values (for a result's `params`)."""
    out = {}
    for f in dataclasses.fields(params):
        v = getattr(params, f.name)
        if hasattr(v, "tolist"):
            v = v.tolist()
        out[f.name] = v
    return out


def _attribute_docs(cls: type) -> dict[str, tuple[str, int]]:
    """Field name -> (text, names sharing it) from the `Attributes:` sections of `cls` and its bases (Google style).

    An entry is `name: text` (continuation lines indented deeper); `a, b: text` documents several
    fields at once; several `name: text` entries may share one line ("n_train: ...; n_bins: ...").
    """
    import inspect
    import re

    out: dict[str, tuple[str, int]] = {}
    for klass in reversed(cls.__mro__):
        doc = inspect.getdoc(klass) or ""
        if klass.__doc__ is None or "Attributes:" not in doc:
            continue
        body = doc.split("Attributes:", 1)[1].splitlines()
        entries: list[tuple[list[str], str]] = []
        base = None
        for line in body:
            if not line.strip():
                continue
            indent = len(line) - len(line.lstrip())
            if base is None:
                base = indent
            if indent < base:
                break
            m = re.match(r"^([A-Za-z_][\w]*(?:\s*,\s*[A-Za-z_][\w]*)*)\s*:\s*(.*)$", line.strip())
            if indent == base and m:
                entries.append(([n.strip() for n in m.group(1).split(",")], m.group(2)))
            elif entries:
                names, text = entries[-1]
                entries[-1] = (names, text + " " + line.strip())
        for names, text in entries:
            # "a: x. b: y" on one line: split where another documented-looking name follows
            parts = re.split(r"(?<=[.;])\s+([A-Za-z_]\w*(?:\s*,\s*[A-Za-z_]\w*)*):\s", text)
            pieces = [(names, parts[0])]
            for i in range(1, len(parts) - 1, 2):
                pieces.append(([n.strip() for n in parts[i].split(",")], parts[i + 1]))
            for ns, t in pieces:
                t = " ".join(t.split())
                for n in ns:
                    if n in out and t.lower().startswith(("as for", "as in", "see ")):
                        continue  # a subclass pointing back at the base's text: keep the base's
                    out[n] = (t, len(ns))
    return out


def describe(defaults: Any) -> list[dict[str, Any]]:
    """Each parameter of a params dataclass / eqx.Module instance: name, default, unit, one-line meaning.

    Generated from the fields (defaults) and the class docstring's `Attributes:` section (meaning; the
    unit is the first `[...]` of the text, e.g. `[m]`).
    """
    import re

    docs = _attribute_docs(type(defaults))
    rows = []
    for f in dataclasses.fields(defaults):
        text, shared = docs.get(f.name, ("", 1))
        unit = _unit_of_name(f.name)
        bracket = re.search(r"\[([^\]]+)\]", text)
        if not unit and bracket and shared == 1:
            unit = bracket.group(1)
        meaning = re.sub(r"\s*\[[^\]]+\]", "", _first_sentence(text)).strip()
        v = getattr(defaults, f.name)
        if hasattr(v, "tolist"):
            v = v.tolist()
        rows.append({"name": f.name, "default": v, "unit": unit, "meaning": meaning})
    return rows


_UNITS = (("_m2", "m^2"), ("_m", "m"), ("_s", "s"), ("_hz", "Hz"), ("_dbm", "dBm"), ("_deg", "deg"))


def _unit_of_name(name: str) -> str:
    for suffix, unit in _UNITS:
        if name.endswith(suffix):
            return unit
    return ""


def _first_sentence(text: str, width: int = 110) -> str:
    """The text up to the first '. ' outside parentheses, cut to `width` characters at a word."""
    depth, end = 0, len(text)
    for i, ch in enumerate(text):
        if ch in "([":
            depth += 1
        elif ch in ")]":
            depth = max(depth - 1, 0)
        elif ch in ".;" and depth == 0 and (i + 1 == len(text) or text[i + 1] == " "):
            word = text[:i].rsplit(" ", 1)[-1].lower().lstrip("(")
            if ch == "." and word in ("eq", "eqs", "e.g", "i.e", "cf", "vs", "fig", "approx", "sec"):
                continue  # an abbreviation, not the end of the sentence
            end = i
            break
    out = text[:end].strip()
    if len(out) > width:
        out = out[: width - 3].rsplit(" ", 1)[0].rstrip(",;:(") + "..."
    return out
