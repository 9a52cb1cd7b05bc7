"""The documents other tools read are strict JSON: a missing number is null, never a bare NaN."""

import json

import numpy as np
import pytest

from reports.jsondoc import json_text


def test_non_finite_numbers_become_null_and_the_text_is_strict_json():
    doc = {
        "p50": float("nan"),
        "max": np.float32("inf"),
        "rate": np.float64(0.5),
        "n": np.int64(3),
        "grid": np.array([1.0, np.nan]),
        "nested": [{"x": -float("inf")}, (1, 2)],
        "reason": None,
    }
    text = json_text(doc, sort_keys=True)

    def refuse(token):
        raise AssertionError(token)

    back = json.loads(text, parse_constant=refuse)
    assert back == {
        "p50": None,
        "max": None,
        "rate": 0.5,
        "n": 3,
        "grid": [1.0, None],
        "nested": [{"x": None}, [1, 2]],
        "reason": None,
    }
    assert text.endswith("}\n")


def test_what_json_cannot_hold_is_an_error_not_a_guess():
    with pytest.raises(TypeError):
        json_text({"when": object()})
