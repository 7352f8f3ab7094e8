"""JSON that other tools can read: NaN and infinities become null, NumPy scalars and arrays plain Python."""

from __future__ import annotations

import math
from typing import Any


def json_safe(x: Any) -> Any:
    """JSON-safe copy of `x`: NaN/inf -> None, NumPy scalars and arrays -> Python, dict keys -> str."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if hasattr(x, "tolist"):
        return json_safe(x.tolist())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
