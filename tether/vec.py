"""Short vectors (a vehicle's 2 or 3 axes) as lists of Python floats. Pure.

The agent's tick, its supervisor, the failsafe laws and a plant's watchdog work on samples as they
come off the wire (lists), one IEEE operation at a time in the order numpy's element-wise
operations take: a numpy temporary per operation on a 3-vector cost more than the arithmetic.
A dot product adds its terms in order, as numpy's does for vectors this short (``d <= 8``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

Vec = Sequence[float]
"""``d`` floats: a list, or anything with ``tolist`` (a numpy array)."""


def floats(x: Vec | Any) -> list[float]:
    """``x`` as a list of Python floats: ``x`` itself if it is a list already (samples off the
    wire, the tick's own vectors: not copied again on the hot path), an array's ``tolist``, else a
    new list. A caller that keeps the result while ``x`` may change copies it."""
    if type(x) is list:
        return x
    tolist = getattr(x, "tolist", None)
    return tolist() if tolist is not None else [float(c) for c in x]


def rows(x: Sequence[Vec] | Any) -> list[list[float]]:
    """A sequence of vectors (or a 2-D array) as lists of Python floats (lists kept as they are)."""
    tolist = getattr(x, "tolist", None)
    return tolist() if tolist is not None else [floats(r) for r in x]


def dot(x: Vec, y: Vec) -> float:
    """``x . y``, the products added in order (NaN or infinite exactly when a term is)."""
    n = len(x)
    if n == 3 and len(y) == 3:  # the same additions, left to right, without the loop (the hot path)
        return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]
    if n == 2 and len(y) == 2:
        return x[0] * y[0] + x[1] * y[1]
    acc = 0.0
    first = True
    for a, b in zip(x, y):
        if first:
            acc, first = a * b, False
        else:
            acc += a * b
    return acc


def norm(x: Vec) -> float:
    """``|x|``: the squares added in order (``x . x`` as :func:`dot` adds it); infinite if a component
    is not finite (a NaN one makes the sum NaN). Self-contained, so that the in-process engine's
    twin compiles this very function (``sim/lockstep_kernel.py``), on a row of its arrays."""
    n = len(x)
    if n == 3:  # the hot path: the same additions, left to right, without the loop
        sq = x[0] * x[0] + x[1] * x[1] + x[2] * x[2]
    elif n == 2:
        sq = x[0] * x[0] + x[1] * x[1]
    else:
        sq = x[0] * x[0]
        for c in range(1, n):
            sq = sq + x[c] * x[c]
    return math.sqrt(sq) if sq == sq else math.inf
