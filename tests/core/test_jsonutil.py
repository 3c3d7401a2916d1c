"""stereodem.core.jsonutil: every JSON file is strict JSON (no NaN or Infinity)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from helpers.strict_json import strict_loads

from stereodem.core import jsonutil


def test_non_finite_numbers_become_null_and_numpy_values_plain_numbers():
    record = {
        "nmad": float("nan"),
        "ratio": math.inf,
        "median": np.float32(-0.5),
        "n": np.int64(7),
        "ok": np.bool_(True),
        "ranks": np.array([1.0, np.nan, -np.inf]),
        "pair": (1, np.float64(np.nan)),
        3: "an int key",
        "path": Path("out/dem.tif"),
    }
    text = jsonutil.dumps(record)
    assert text.endswith("\n")
    back = strict_loads(text)
    assert back == {
        "nmad": None,
        "ratio": None,
        "median": -0.5,
        "n": 7,
        "ok": True,
        "ranks": [1.0, None, None],
        "pair": [1, None],
        "3": "an int key",
        "path": "out/dem.tif",
    }
    with pytest.raises(ValueError, match="not strict JSON"):
        strict_loads(json.dumps({"x": float("nan")}))  # what Python's json writes by default
