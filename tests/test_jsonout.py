"""Strict JSON out: no NaN or infinity ever reaches a file the project writes (``tether.jsonout``)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tether import jsonout


def _strict(text: str) -> object:
    """Parse as a strict JSON parser would: the bare words NaN and Infinity are errors."""
    def refuse(word: str) -> None:
        raise ValueError(f"{word} is not JSON")

    return json.loads(text, parse_constant=refuse)


def test_non_finite_numbers_become_null_and_numpy_scalars_plain() -> None:
    obj = {"a": math.nan, "b": [math.inf, -math.inf, 1.5], "c": np.float64("nan"), "d": np.int64(3),
           "e": (np.bool_(True), np.float32(0.25)), "f": {"g": [[math.nan]]}}
    assert _strict(jsonout.dumps(obj)) == {"a": None, "b": [None, None, 1.5], "c": None, "d": 3,
                                           "e": [True, 0.25], "f": {"g": [[None]]}}
    assert "\n" not in jsonout.dumps(obj, indent=None)


def test_a_default_is_made_finite_too() -> None:
    """The bench reports pass ``default=float`` (numpy arrays' items, load averages...)."""
    class Reading:
        def __float__(self) -> float:
            return math.nan

    assert _strict(jsonout.dumps({"x": Reading(), "y": 2.0}, default=float)) == {"x": None, "y": 2.0}
    assert _strict(jsonout.dumps([Reading()], default=lambda o: [float(o), 1.0])) == [[None, 1.0]]


def test_what_json_cannot_hold_is_refused_not_written() -> None:
    with pytest.raises(TypeError):
        jsonout.dumps({"x": object()})
