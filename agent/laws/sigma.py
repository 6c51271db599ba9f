"""Eq. 17 of Su, Bhowmick & Lanzon (2023): the adaptive formation law with sigma-modification.

Eq. 8, 9:  xi_i   = sum_j a_ij (p_i - p_j - delta_ij) = kappa_i p_i - sum_wp - sum_wdelta
           zeta_i = sum_j a_ij (v_i - v_j)            = kappa_i v_i - sum_wv
Eq. 17:    u_i = (sum_wa - Kp xi_i - Kv zeta_i) / kappa_i          (per-axis gains)
           Kp' = -sigma (Kp - 1) + Gamma_p xi^2,   Kv' = -sigma (Kv - 1) + Gamma_v zeta^2

The gains advance by the exact solution of their ODE over one period ``h`` with the errors held:
``K+ = 1 + (K - 1) decay + Gamma e^2 gain``, ``decay = exp(-sigma h)``,
``gain = (1 - exp(-sigma h)) / sigma`` (``= h`` when sigma = 0). As ``decay <= 1`` and ``gain >= 0``,
``K >= 1`` is preserved in discrete time, as in Theorem 1's proof.
"""

from __future__ import annotations

import math
from typing import Any

import msgspec

from agent.laws import FormationLaw, Problems, axis_problems, per_axis

PerAxis = float | list[float]


def step(ka: Any, p: Any, v: Any, sp: Any, sv: Any, sa: Any, sd: Any, x: tuple[Any, ...],
         c: tuple[Any, ...]) -> tuple[Any, Any, Any, tuple[Any, Any]]:
    """Eq. 17 on one axis (the contract of :mod:`agent.laws`): ``x = (Kp, Kv)`` the gains
    ``K(t_k)``, ``c = (decay, Gamma_p gain, Gamma_v gain)``; returns ``u, xi, zeta, (Kp+, Kv+)``."""
    kp, kv = x
    e = ka * p - sp - sd
    z = ka * v - sv
    u = (sa - kp * e - kv * z) / ka
    return u, e, z, (1.0 + (kp - 1.0) * c[0] + c[1] * (e * e), 1.0 + (kv - 1.0) * c[0] + c[2] * (z * z))


def rate(ka: Any, p: Any, v: Any, sp: Any, sv: Any, sd: Any, b: Any, x: tuple[Any, ...],
         r: tuple[Any, ...]) -> tuple[Any, Any, Any, tuple[Any, Any]]:
    """The continuous-time form (the reference simulator's continuous mode): ``x = (Kp, Kv)``,
    ``r = (sigma, Gamma_p, Gamma_v)``, ``b`` the closed loop's known part ``a_i0 a_ref + kappa d``;
    returns ``b - Kp xi - Kv zeta`` (agent i's row of ``L1 vdot``), ``xi, zeta`` and the gains' rates."""
    kp, kv = x
    e = ka * p - sp - sd
    z = ka * v - sv
    return (b - kp * e - kv * z, e, z,
            (-r[0] * (kp - 1.0) + r[1] * (e * e), -r[0] * (kv - 1.0) + r[2] * (z * z)))


def gain_coefficients(sigma: float, h: float) -> tuple[float, float]:
    """``(decay, gain)`` of the exact gain step over ``h`` [s] with leakage ``sigma`` [1/s]."""
    if sigma == 0.0:
        return 1.0, h
    return math.exp(-sigma * h), -math.expm1(-sigma * h) / sigma


class SigmaParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Eq. 17's parameters: initial gains ``kp0`` [1/s^2 after the 1/kappa scaling], ``kv0`` [1/s]
    and adaptation rates ``gamma_p, gamma_v``, each one number or one per axis; leakage ``sigma`` [1/s]."""

    kp0: PerAxis
    kv0: PerAxis
    gamma_p: PerAxis
    gamma_v: PerAxis
    sigma: float = 0.0


class Sigma(FormationLaw):
    """Eq. 17: the gains adapt with leakage ``sigma`` towards 1."""

    name = "sigma"
    state = ("kp", "kv")
    units = ("1/s^2", "1/s")  # u = -(Kp xi + Kv zeta) / kappa: xi [m], zeta [m/s], u [m/s^2]
    Params = SigmaParams
    step = staticmethod(step)
    rate = staticmethod(rate)
    floor = 1.0
    """The least initial gain (Theorem 1 needs K(0) >= 1)."""

    def check(self, params: Any, dim: int) -> Problems:
        out: Problems = []
        for name in ("kp0", "kv0", "gamma_p", "gamma_v"):
            out += axis_problems(getattr(params, name), dim, name)
        if out:
            return out
        why = "Theorem 1 needs K(0) >= 1 for the sigma law" if self.floor == 1.0 else "Eq. 30 needs K(0) >= 0"
        for name in ("kp0", "kv0", "gamma_p", "gamma_v"):
            val = getattr(params, name)
            for k, x in enumerate(per_axis(val, dim)):
                field = name + (f"[{k}]" if isinstance(val, list) else "")
                if name.startswith("k") and x < self.floor:
                    out.append((field, f"is {x}, below {self.floor:g} ({why}); raise it to >= {self.floor:g}"))
                elif name.startswith("gamma") and not x > 0:
                    out.append((field, f"is {x}; set an adaptation rate > 0, e.g. `{name} = 0.05`"))
                if not isinstance(val, list):
                    break
        return out

    def initial(self, params: Any, dim: int) -> tuple[tuple[float, ...], ...]:
        return per_axis(params.kp0, dim), per_axis(params.kv0, dim)

    def coefficients(self, params: Any, h: float, dim: int) -> tuple[tuple[float, ...], ...]:
        decay, gain = gain_coefficients(float(params.sigma), h)
        return tuple((decay, gp * gain, gv * gain)
                     for gp, gv in zip(per_axis(params.gamma_p, dim), per_axis(params.gamma_v, dim)))

    def rates(self, params: Any, dim: int) -> tuple[tuple[float, ...], ...]:
        """Per axis, the coefficients ``r`` of :func:`rate`."""
        return tuple((float(params.sigma), gp, gv)
                     for gp, gv in zip(per_axis(params.gamma_p, dim), per_axis(params.gamma_v, dim)))
