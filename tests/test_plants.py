"""The plant contract: every plant a mission can name behaves the same way through
:class:`plant.base.Plant` (shapes, tick 0, determinism, what a command does, closing)."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from plant import base

from plant.build import build
from tether import mission as ms
from tether.catalog import builtin_path


def mission(kind: str) -> ms.Mission:
    """Experiment 1's four vehicles on plant ``kind``; ``payload``: Experiment 2's world."""
    if kind == "payload":
        return ms.load(builtin_path("exp2"))
    m = ms.load(builtin_path("exp1"))
    spec = {"double_integrator": ms.DoubleIntegrator(), "point_mass": ms.PointMassPlant(),
            "quadrotor": ms.QuadrotorPlant()}[kind]
    return msgspec.structs.replace(m, agents=[msgspec.structs.replace(a, plant=spec) for a in m.agents])


KINDS = ["double_integrator", "point_mass", "quadrotor", "payload"]


def fly(m: ms.Mission, u: np.ndarray, ticks: int) -> list[base.Sample]:
    hosts = build(m)
    out = []
    for _ in range(ticks):
        samples = [h.state() for h in hosts]
        out.append(samples)
        for h in hosts:
            h.step(np.array([u[m.agent_ids.index(i)] for i in h.ids]))
    for h in hosts:
        h.close()
        h.close()  # closing twice is harmless
    return out


@pytest.mark.parametrize("kind", KINDS)
def test_every_plant_keeps_the_contract(kind: str) -> None:
    m = mission(kind)
    hosts = build(m)
    assert sorted(i for h in hosts for i in h.ids) == sorted(m.agent_ids)
    for h in hosts:
        assert isinstance(h, base.Plant)
        s = h.state()
        n = len(h.ids)
        for name in ("p", "v", "a", "d"):
            assert getattr(s, name).shape == (n, m.dim), name
            assert np.all(np.isfinite(getattr(s, name))), name
        np.testing.assert_array_equal(s.a, 0.0)  # nothing measured before the first period
        np.testing.assert_allclose(s.p, [m.agent(i).p0 for i in h.ids])  # starts where the mission says
    # deterministic: the same commands give the same samples, bit for bit
    u = np.tile([0.2, -0.1, 0.3], (m.n, 1))
    a, b = fly(m, u, 50), fly(m, u, 50)
    for ra, rb in zip(a, b):
        for sa, sb in zip(ra, rb):
            for name in ("p", "v", "a", "d"):
                np.testing.assert_array_equal(getattr(sa, name), getattr(sb, name))


@pytest.mark.parametrize("kind, tol", [("double_integrator", 1e-12), ("point_mass", 1e-12), ("quadrotor", 0.05)])
def test_a_held_command_is_the_measured_acceleration(kind: str, tol: float) -> None:
    """Without disturbance, ``a`` reported at tick k is the mean acceleration over the previous
    period, and for a vehicle that flies its command it is that command (the quadrotor once its
    inner loop has settled: Remark 1)."""
    m = mission(kind)
    u = np.tile([0.3, -0.2, 0.1], (m.n, 1))
    samples = fly(m, u, 300)
    last = samples[-1][0] if len(samples[-1]) == 1 else None
    got = np.vstack([s.a for s in samples[-1]]) if last is None else last.a
    np.testing.assert_allclose(got, u, atol=tol)
    # and a consistent with the velocity's change over the period
    h = m.dt
    v1 = np.vstack([s.v for s in samples[-1]])
    v0 = np.vstack([s.v for s in samples[-2]])
    np.testing.assert_allclose(got, (v1 - v0) / h, atol=1e-9)


def test_the_payload_world_reports_its_cables() -> None:
    m = mission("payload")
    (world,) = build(m)
    s = world.state()
    assert s.payload.tension.shape == (m.n,) and s.payload.p.shape == (3,)
    np.testing.assert_array_equal(s.payload.tension, 0.0)  # on the floor, cables slack
    assert s.payload.p[2] == m.floor


@pytest.mark.slow  # a software Crazyflie
def test_the_crazyflie_plant_keeps_the_contract() -> None:
    """A live plant: the same interface and shapes, a reading that is the vehicle's own, and
    closing (landing) that may be repeated. (Tick 0's zero acceleration and determinism are
    properties of simulated plants only.)"""
    pytest.importorskip("cflib.crtp")
    from tests.support import free_port
    from tests.test_crazyflie import software_crazyflies

    port = free_port(udp=True)
    m = mission("quadrotor")
    spec = ms.CrazyfliePlant(uri=f"udp://127.0.0.1:{port}", takeoff_height=0.6)
    m = msgspec.structs.replace(m, agents=[msgspec.structs.replace(a, plant=spec) for a in m.agents])
    with pytest.raises(ValueError, match="real vehicle"):
        build(m)  # never inside a simulator
    with software_crazyflies([port], [(0.0, 0.0, 0.0)]):
        (plant,) = build(m, [1], live=True)
        plant.open()  # build leaves a real vehicle unconnected (opening blocks)
        try:
            assert isinstance(plant, base.Plant) and plant.ids == (1,)
            s = plant.state()
            for name in ("p", "v", "a"):
                assert getattr(s, name).shape == (1, 3) and np.all(np.isfinite(getattr(s, name))), name
            assert s.d.shape == (1, 3) and np.all(np.isnan(s.d))  # a real vehicle cannot know its disturbance
            plant.step(np.zeros((1, 3)))
        finally:
            plant.close()
            plant.close()
