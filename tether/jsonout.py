"""JSON output files (metrics, sweep tables, a run's events and faults, netem logs, replies, bench
reports): strict JSON, with nothing JSON cannot hold. Pure. Every JSON the project writes goes
through :func:`dumps`.

Python's ``json`` writes NaN and infinity as the bare words ``NaN`` and ``Infinity``, which no JSON
parser but Python's accepts. :func:`dumps` writes them as ``null`` instead (a metric with no
value: a diverged run, an empty window) and numpy scalars as plain numbers, and refuses anything
else that is not JSON (``allow_nan=False`` is then only a guard).
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Callable
from typing import Any

__all__ = ["dumps", "finite"]


def finite(obj: object) -> object:
    """``obj`` with numpy scalars made plain and every non-finite float replaced by None.

    numpy is not imported here: a process that never loaded it (an agent answering a netem query)
    holds no numpy scalar, and an agent's memory is the smaller by numpy's 13 MiB."""
    np = sys.modules.get("numpy")
    if np is not None and isinstance(obj, (np.floating, np.integer, np.bool_)):
        obj = obj.item()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    return obj


def dumps(obj: object, indent: int | None = 2, default: Callable[[Any], object] | None = None) -> str:
    """``obj`` as strict JSON text (see the module docstring); raises TypeError for a non-JSON value.
    ``default``: as :func:`json.dumps`'s (a value for an object JSON cannot hold), its result made
    :func:`finite` too."""
    fallback = None if default is None else (lambda o: finite(default(o)))
    return json.dumps(finite(obj), indent=indent, allow_nan=False, default=fallback)
