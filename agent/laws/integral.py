"""Eq. 17 with integral action: the adaptive law of Su, Bhowmick & Lanzon (2023) plus a distributed
integral of the formation error, which removes a constant disturbance.

The integral of each agent's own formation error (Eq. 8's ``xi_i``, a relative quantity built from
its in-neighbours' samples only) is the distributed integral action of

    M. Andreasson, D. V. Dimarogonas, H. Sandberg and K. H. Johansson, "Distributed control of
    networked dynamical systems: static feedback, integral action and consensus", IEEE
    Transactions on Automatic Control 59(7):1750-1764, 2014,

applied here to a graph rooted at a virtual leader, which pins the integrators' equilibrium
(no averaging of the integral states between agents is needed):

    xi_i   = kappa_i p_i - sum_wp - sum_wdelta          (Eq. 8)
    zeta_i = kappa_i v_i - sum_wv                       (Eq. 9)
    u_i    = (sum_wa - Kp xi_i - Kv zeta_i - k_I s_i) / kappa_i
    Kp', Kv' as Eq. 17 (sigma-modified adaptation)
    s_i'   = xi_i - lambda s_i (s_i / S)^16,   S = a_I / k_I

With a constant disturbance ``d_i`` the equilibrium has ``k_I s_i = kappa_i d_i`` and
``xi_i = lambda s_i (s_i / S)^16``: zero up to a term of order 16 in ``kappa_i d_i / a_I`` (for
``kappa d = a_I / 2`` it is ``1.5e-5 lambda s_i``). The last term is a soft anti-windup bound:
negligible well inside ``|k_I s| < a_I`` [m/s^2], a strong leak beyond it, so that a vehicle that
cannot follow its command (saturated at ``safety.max_accel``, or held by something) does not wind
its integrator up without bound. It is written with ``+ - * /`` only (the contract of
:mod:`agent.laws` has no ``min`` or ``abs``), and stepped semi-implicitly,
``s+ = (s + h xi) / (1 + h lambda (s / S)^16)``, which is stable for every ``s`` and every ``h``.

Too large a ``k_I`` destabilises the loop: linearised at held gains, a mode of eigenvalue ``mu``
of ``K^-1 L1`` is stable only while ``k_I < Kp Kv mu`` (real ``mu``; docs/laws.md, "Choosing ki").

Like every law's state, ``s`` advances only while the supervisor's mode is FLYING: in HOLD, LAND
or on the ground it keeps the value it had, and the law resumes from it.
"""

from __future__ import annotations

import math
from typing import Any

import msgspec

from agent.laws import FormationLaw, Problems, axis_problems, per_axis
from agent.laws.sigma import PerAxis, Sigma, gain_coefficients


def step(ka: Any, p: Any, v: Any, sp: Any, sv: Any, sa: Any, sd: Any, x: tuple[Any, ...],
         c: tuple[Any, ...]) -> tuple[Any, Any, Any, tuple[Any, Any, Any]]:
    """One axis (the contract of :mod:`agent.laws`): ``x = (Kp, Kv, s)`` with ``s`` the integral of
    ``xi`` [m s]; ``c = (decay, Gamma_p gain, Gamma_v gain, h, k_I, h lambda, 1 / S)``; returns
    ``u`` [m/s^2], ``xi``, ``zeta`` and ``(Kp+, Kv+, s+)``."""
    kp, kv, s = x
    e = ka * p - sp - sd
    z = ka * v - sv
    u = (sa - kp * e - kv * z - c[4] * s) / ka
    r = s * c[6]
    r2 = r * r
    r4 = r2 * r2
    r8 = r4 * r4
    return u, e, z, (1.0 + (kp - 1.0) * c[0] + c[1] * (e * e), 1.0 + (kv - 1.0) * c[0] + c[2] * (z * z),
                     (s + c[3] * e) / (1.0 + c[5] * (r8 * r8)))


def rate(ka: Any, p: Any, v: Any, sp: Any, sv: Any, sd: Any, b: Any, x: tuple[Any, ...],
         r: tuple[Any, ...]) -> tuple[Any, Any, Any, tuple[Any, Any, Any]]:
    """The continuous-time form: ``x = (Kp, Kv, s)``, ``r = (sigma, Gamma_p, Gamma_v, k_I, lambda,
    1 / S)``; returns agent i's row of ``L1 vdot``, ``xi``, ``zeta`` and the state's rates."""
    kp, kv, s = x
    e = ka * p - sp - sd
    z = ka * v - sv
    q = s * r[5]
    q2 = q * q
    q4 = q2 * q2
    q8 = q4 * q4
    return (b - kp * e - kv * z - r[3] * s, e, z,
            (-r[0] * (kp - 1.0) + r[1] * (e * e), -r[0] * (kv - 1.0) + r[2] * (z * z),
             e - r[4] * s * (q8 * q8)))


class IntegralParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Eq. 17's parameters (initial gains ``kp0`` [1/s^2 after the 1/kappa scaling], ``kv0`` [1/s],
    rates ``gamma_p, gamma_v``, leakage ``sigma`` [1/s]) and the integral action's."""

    kp0: PerAxis
    kv0: PerAxis
    gamma_p: PerAxis
    gamma_v: PerAxis
    ki: PerAxis
    """Integral gain ``k_I`` [1/s^3 after the 1/kappa scaling], one or one per axis; > 0."""
    integral_limit: float
    """Soft bound ``a_I`` on the integral term ``|k_I s|`` [m/s^2]; > 0. Give it room above the
    largest ``kappa_i |d_i|`` to cancel: the steady error is ``lambda s (kappa d / a_I)^16`` [m]."""
    sigma: float = 1.0
    """Leakage of the gains' adaptation [1/s], as Eq. 17's; >= 0 (0: Eq. 30's adaptation)."""
    limit_rate: float = 1.0
    """``lambda`` [1/s]: the integrator's leak rate at ``|k_I s| = a_I``; > 0."""


class Integral(FormationLaw):
    """Eq. 17 plus a soft-bounded integral of the formation error (module docstring)."""

    name = "integral"
    state = ("kp", "kv", "s")
    units = ("1/s^2", "1/s", "m s")  # s integrates xi [m]
    Params = IntegralParams
    step = staticmethod(step)
    rate = staticmethod(rate)

    def check(self, params: Any, dim: int) -> Problems:
        out = Sigma().check(params, dim) + axis_problems(params.ki, dim, "ki")  # Eq. 17's fields as Eq. 17's
        if not axis_problems(params.ki, dim, "ki"):
            for k, g in enumerate(per_axis(params.ki, dim)):
                if not (g > 0 and math.isfinite(g)):
                    field = "ki" + (f"[{k}]" if isinstance(params.ki, list) else "")
                    out.append((field, f"is {g}; the integral gain must be finite and > 0, and below Kp Kv mu_min "
                                       "(docs/laws.md, Choosing ki; e.g. ki = 0.2)"))
                    break
        if not params.sigma >= 0 or not math.isfinite(params.sigma):
            out.append(("sigma", f"is {params.sigma}; the leakage must be finite and >= 0 (e.g. sigma = 1.0)"))
        if not (params.integral_limit > 0 and math.isfinite(params.integral_limit)):
            out.append(("integral_limit", f"is {params.integral_limit}; bound the integral term with a finite "
                                          "acceleration > 0 [m/s^2], above the largest disturbance to cancel "
                                          "(e.g. integral_limit = 4.0)"))
        if not (params.limit_rate > 0 and math.isfinite(params.limit_rate)):
            out.append(("limit_rate", f"is {params.limit_rate}; the leak rate at the limit must be finite and > 0 "
                                      "[1/s] (e.g. limit_rate = 1.0)"))
        return out

    def initial(self, params: Any, dim: int) -> tuple[tuple[float, ...], ...]:
        return per_axis(params.kp0, dim), per_axis(params.kv0, dim), (0.0,) * dim

    def coefficients(self, params: Any, h: float, dim: int) -> tuple[tuple[float, ...], ...]:
        decay, gain = gain_coefficients(float(params.sigma), h)
        lam = float(params.limit_rate)
        return tuple((decay, gp * gain, gv * gain, h, ki, h * lam, ki / float(params.integral_limit))
                     for gp, gv, ki in zip(per_axis(params.gamma_p, dim), per_axis(params.gamma_v, dim),
                                           per_axis(params.ki, dim)))

    def rates(self, params: Any, dim: int) -> tuple[tuple[float, ...], ...]:
        return tuple((float(params.sigma), gp, gv, ki, float(params.limit_rate), ki / float(params.integral_limit))
                     for gp, gv, ki in zip(per_axis(params.gamma_p, dim), per_axis(params.gamma_v, dim),
                                           per_axis(params.ki, dim)))
