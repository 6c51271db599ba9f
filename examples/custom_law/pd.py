"""A formation law of one's own: PD consensus with fixed per-axis gains (no adaptation).

    u_i = (sum_j a_ij a_j - kp xi_i - kv zeta_i) / kappa_i

with ``xi_i``, ``zeta_i`` the formation and velocity errors of Eq. 8, 9. It is Eq. 17 with its gains
frozen: a baseline to set beside the adaptive laws. A mission runs it with

    [law]
    use = "examples.custom_law.pd:PDConsensus"
    params = { kp = 2.0, kv = [2.0, 3.0] }

(see docs/laws.md for the contract, and mission.toml beside this file).
"""

from __future__ import annotations

from typing import Any

import msgspec

from agent.laws import FormationLaw, Problems, axis_problems, per_axis


class PDParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """``kp`` [1/s^2 after the 1/kappa scaling] and ``kv`` [1/s]: one number, or one per axis."""

    kp: float | list[float]
    kv: float | list[float]


def pd_step(ka: Any, p: Any, v: Any, sp: Any, sv: Any, sa: Any, sd: Any, x: tuple[()],
            c: tuple[Any, Any]) -> tuple[Any, Any, Any, tuple[()]]:
    """One axis of one agent: ``c = (kp, kv)``; no state (``x`` and the next state are empty)."""
    e = ka * p - sp - sd
    z = ka * v - sv
    return (sa - c[0] * e - c[1] * z) / ka, e, z, ()


class PDConsensus(FormationLaw):
    """PD consensus with fixed gains."""

    name = "pd"
    state = ()
    Params = PDParams
    step = staticmethod(pd_step)

    def check(self, params: Any, dim: int) -> Problems:
        out = axis_problems(params.kp, dim, "kp") + axis_problems(params.kv, dim, "kv")
        for name in ("kp", "kv"):
            value = getattr(params, name)
            for k, g in enumerate((value if isinstance(value, list) else [value]) if not out else []):
                if not g > 0:
                    field = name + (f"[{k}]" if isinstance(value, list) else "")
                    out.append((field, f"is {g}; a PD gain must be > 0 (e.g. {name} = 2.0)"))
        return out

    def coefficients(self, params: Any, h: float, dim: int) -> tuple[tuple[float, ...], ...]:
        return tuple(zip(per_axis(params.kp, dim), per_axis(params.kv, dim)))
