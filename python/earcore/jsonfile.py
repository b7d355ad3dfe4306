"""JSON that every reader parses: Python's `json` writes NaN and infinities as `NaN` and
`Infinity`, which the JSON standard (and `JSON.parse`, `jq`) rejects. Here a value that
is not a finite number (no measurement, no bound) is written as `null`; numpy scalars and
arrays as numbers and lists."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

__all__ = ["dumps", "plain"]


def plain(value: Any) -> Any:
    """`value` with numpy types as Python's and every non-finite float as None."""
    if isinstance(value, dict):
        return {key: plain(v) for key, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def dumps(data: Any, **kwargs: Any) -> str:
    """`json.dumps` of `plain(data)`, strict: standard JSON or an error."""
    return json.dumps(plain(data), allow_nan=False, **kwargs)
