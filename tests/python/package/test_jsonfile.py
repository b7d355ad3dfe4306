"""The JSON files earcore writes are standard JSON: what is not a finite number is null."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from earcore import jsonfile


def strict(text: str):
    def refuse(constant):
        raise ValueError(f"{constant} is not JSON")

    return json.loads(text, parse_constant=refuse)


def test_non_finite_numbers_become_null_and_numpy_values_numbers():
    data = {
        "nan": math.nan, "inf": -math.inf, "np_nan": np.float32("nan"), "ok": 1.5, "int": np.int64(3),
        "flag": np.bool_(True), "array": np.array([[1.0, np.inf], [np.nan, 2.0]]), "nested": [{"t": (math.inf, 2)}],
        "text": "NaN",
    }
    assert strict(jsonfile.dumps(data)) == {
        "nan": None, "inf": None, "np_nan": None, "ok": 1.5, "int": 3, "flag": True,
        "array": [[1.0, None], [None, 2.0]], "nested": [{"t": [None, 2]}], "text": "NaN",
    }
    # Python's own writer is what this replaces: it writes what JSON readers reject.
    with pytest.raises(ValueError, match="NaN is not JSON"):
        strict(json.dumps({"x": math.nan}))


def test_what_json_cannot_hold_is_still_an_error():
    with pytest.raises(TypeError):
        jsonfile.dumps({"x": object()})
