"""Results files are strict JSON: a refused estimate's NaN is written null, numpy's
values as the numbers they hold, and every JSON reader loads the text."""
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from semservo import jsontext


@dataclass
class Row:
    error_deg: float
    sweeps: int


def test_numbers_that_are_not_finite_are_written_null_and_the_rest_as_they_are():
    value = {"mean": math.nan, "max": np.float32(np.inf), "low": -math.inf, "poses": np.int64(33),
             "errors": np.array([0.5, np.nan]), "pose": (1.5, np.float64(-2.0)), "ok": np.bool_(True),
             "row": Row(math.nan, 4), "file": Path("bench/results/tilt.json"), "name": None}
    text = jsontext.dumps(value, indent=1)
    assert "NaN" not in text and "Infinity" not in text
    # A strict reader (one that refuses NaN and Infinity, as browsers' JSON.parse does) loads it.
    loaded = json.loads(text, parse_constant=lambda token: pytest.fail(f"not JSON: {token}"))
    assert loaded == {"mean": None, "max": None, "low": None, "poses": 33, "errors": [0.5, None],
                      "pose": [1.5, -2.0], "ok": True, "row": {"error_deg": None, "sweeps": 4},
                      "file": "bench/results/tilt.json", "name": None}
    assert type(loaded["poses"]) is int and type(loaded["ok"]) is bool


def test_what_has_no_json_form_is_refused_as_json_refuses_it():
    with pytest.raises(TypeError):
        jsontext.dumps({"set": {1, 2}})
