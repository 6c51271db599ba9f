"""The plants of a mission: which :mod:`plant.base` plant (or real vehicle) hosts which agents. Pure,
but for a real vehicle's driver, loaded only when a mission flies one."""

from __future__ import annotations

from plant.base import DoubleIntegratorPlant, PayloadPlant, Plant, VehiclePlant
from tether import mission as ms


def build(m: ms.Mission, ids: list[int] | None = None, live: bool = False) -> list[Plant]:
    """The plants hosting agents ``ids`` (all by default): one :class:`PayloadPlant` for a payload
    mission (which must host all of them), else one plant per agent. ``live``: the caller runs in
    real time (a plant process), so real vehicles (``crazyflie``) may be built; they are returned
    unconnected, for the caller to :meth:`~plant.crazyflie.CrazyfliePlant.open` (it blocks: the
    plant process runs it in a thread)."""
    ids = m.agent_ids if ids is None else list(ids)
    if m.payload is not None:
        return [PayloadPlant(m, ids)]
    out: list[Plant] = []
    for aid in ids:
        spec = m.agent(aid).plant
        if isinstance(spec, ms.CrazyfliePlant):
            if not live:
                raise ValueError(f"agent {aid}'s plant is a crazyflie, a real vehicle: it flies in real time "
                                 "(tether run --clock realtime), not in a simulator")
            from plant.crazyflie import CrazyfliePlant

            out.append(CrazyfliePlant(m, [aid]))  # not connected: the caller opens it (blocking)
            continue
        out.append(DoubleIntegratorPlant(m, [aid]) if isinstance(spec, ms.DoubleIntegrator) else VehiclePlant(m, [aid]))
    return out
