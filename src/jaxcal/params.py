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
