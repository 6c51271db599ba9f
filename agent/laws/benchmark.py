"""Eq. 30 of Su, Bhowmick & Lanzon (2023), the benchmark law: Eq. 17 without leakage.

``Kp' = Gamma_p xi^2``, ``Kv' = Gamma_v zeta^2`` with per-axis rates (``diag(Gamma_p)``): its
gains can only grow. The step is Eq. 17's (:func:`agent.laws.sigma.step`) with the coefficients
``decay = 1``, ``Gamma h``: the same arithmetic, so the two laws' runs differ only by their numbers.
"""

from __future__ import annotations

from typing import Any

import msgspec

from agent.laws import Problems
from agent.laws.sigma import PerAxis, Sigma


class BenchmarkParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Eq. 30's parameters: initial gains ``kp0, kv0`` and adaptation rates ``gamma_p, gamma_v``,
    each one number or one per axis."""

    kp0: PerAxis
    kv0: PerAxis
    gamma_p: PerAxis
    gamma_v: PerAxis
    sigma: float = 0.0
    """Always 0 (the field lets Eq. 17's coefficients read it)."""


class Benchmark(Sigma):
    """Eq. 30: Eq. 17 with sigma = 0."""

    name = "benchmark"
    Params = BenchmarkParams  # type: ignore[assignment]  # Eq. 30's own fields
    floor = 0.0

    def check(self, params: Any, dim: int) -> Problems:
        out = super().check(params, dim)
        if params.sigma != 0.0:
            out.append(("sigma", "is set but the benchmark law (Eq. 30) has no sigma; remove it, or use "
                                 "kind = \"sigma\""))
        return out
