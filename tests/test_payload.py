"""The cable-suspended payload world (plant/payload.py) and its point-mass vehicle (plant/vehicle.py).

References are independent of the code under test: closed-form free fall and constant-force
motion, a fine-step RK4 of the integrator's ODE, the linear oscillator's decay rate, force balance,
and the energy integral written out here from the bodies' states.
"""

from __future__ import annotations

import numpy as np
import pytest

from plant.payload import CableArrays, CableParams, PayloadWorld, cable_forces, frequency_bound, hover_equilibrium
from plant.vehicle import G, Integrator, PointMass, Vehicle

M_V = 0.030  # vehicle [kg] (a Crazyflie 2.1 with deck and battery)
M_L = 0.015  # payload [kg] (Bitcraze's recommended maximum)
L0 = 0.6  # cable rest length [m]
H = 0.01  # control period [s] (100 Hz)
SQUARE = np.array([[0.35, 0.35, 1.0], [-0.35, 0.35, 1.0], [-0.35, -0.35, 1.0], [0.35, -0.35, 1.0]])


def _square(**kw) -> list[PointMass]:
    return [PointMass(M_V, p, **kw) for p in SQUARE]


def _energy(w: PayloadWorld, k: float, hold_force: np.ndarray | None = None) -> float:
    """Kinetic + payload gravity + elastic (+ potential of constant forces -hold_force on the vehicles)."""
    p, v, pl, vl = w.p, w.v, w.payload_p, w.payload_v
    e = 0.5 * M_V * float((v * v).sum()) + 0.5 * M_L * float(vl @ vl) + M_L * G * pl[2]
    s = np.maximum(np.linalg.norm(p - pl, axis=1) - L0, 0.0)
    e += 0.5 * k * float((s * s).sum())
    if hold_force is not None:
        e += float((hold_force * p).sum())
    return e


# -- the vehicle ------------------------------------------------------------------------------

def test_point_mass_is_eq5_with_the_cable_as_disturbance() -> None:
    veh = PointMass(M_V, [1.0, 2.0, 3.0], [0.1, -0.2, 0.3])
    assert isinstance(veh, Vehicle)
    u, f, t = np.array([0.4, -0.5, 0.6]), np.array([0.01, 0.02, -0.03]), 0.37
    veh.command(u)
    veh.advance(t, f)
    a = u + f / M_V
    p0, v0 = np.array([1.0, 2.0, 3.0]), np.array([0.1, -0.2, 0.3])
    np.testing.assert_allclose(veh.p, p0 + t * v0 + 0.5 * t * t * a, rtol=0, atol=1e-15)
    np.testing.assert_allclose(veh.v, v0 + t * a, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(veh.accel(), a)  # u + f/m to the last bit
    veh.advance(t)  # no force: p'' = u
    np.testing.assert_array_equal(veh.accel(), u)


def test_feedforward_mass_is_eq4_with_the_payload_share_added() -> None:
    m_ff = 0.25 * M_L
    veh = PointMass(M_V, [0.0, 0.0, 1.0], feedforward_mass=m_ff)
    u = np.array([0.3, -0.2, 0.5])
    veh.command(u)
    veh.advance(0.01)  # thrust (m + m_ff)(u + g e_z), weight m g: p'' = u + (m_ff/m)(u + g e_z)
    np.testing.assert_allclose(veh.accel(), u + m_ff / M_V * (u + [0.0, 0.0, G]), rtol=0, atol=1e-14)
    # a share moving rigidly with the vehicle pulls with -m_ff (u + g e_z): the vehicle flies u exactly
    veh.advance(0.01, -m_ff * (u + [0.0, 0.0, G]))
    np.testing.assert_allclose(veh.accel(), u, rtol=0, atol=1e-14)


def _rk4_integrator(m: float, m_ff: float, ki: float, u: np.ndarray, f: np.ndarray, t: float, n: int):
    """Fine-step RK4 of (p, v, I) for the unclamped integrator, as an independent reference."""
    r = 1.0 + m_ff / m

    def rhs(x: np.ndarray) -> np.ndarray:
        a = u + m_ff / m * (u + [0.0, 0.0, G]) + f / m
        a = a + np.array([0.0, 0.0, r * x[6]])
        return np.concatenate([x[3:6], a, [ki * (u[2] - a[2])]])

    x, dt = np.zeros(7), t / n
    for _ in range(n):
        k1 = rhs(x)
        k2 = rhs(x + 0.5 * dt * k1)
        k3 = rhs(x + 0.5 * dt * k2)
        k4 = rhs(x + dt * k3)
        x = x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def test_integrator_matches_rk4_and_removes_the_pull() -> None:
    m_ff, ki = 0.005, 3.0
    u, f = np.array([0.2, 0.0, 0.4]), np.array([0.0, 0.01, -M_L * G])
    veh = PointMass(M_V, [0.0, 0.0, 0.0], feedforward_mass=m_ff, integrator=Integrator(ki, limit=100.0))
    veh.command(u)
    veh.advance(1.5, f)
    ref = _rk4_integrator(M_V, m_ff, ki, u, f, 1.5, 3000)
    np.testing.assert_allclose(veh.p, ref[:3], rtol=0, atol=1e-11)
    np.testing.assert_allclose(veh.v, ref[3:6], rtol=0, atol=1e-11)
    assert veh.integral == pytest.approx(ref[6], abs=1e-11)
    veh.advance(20.0, f)
    veh.advance(0.01, f)  # converged: the vertical command is tracked exactly
    assert veh.accel()[2] == pytest.approx(u[2], abs=1e-9)


def test_integrator_clamp_is_exact_and_splits() -> None:
    """The clamp engages mid-step: one long step equals many short ones (the flow is exact)."""
    f = np.array([0.0, 0.0, -M_L * G])  # pull 4.9 m/s^2 on 30 g, limit 3 m/s^2
    whole = PointMass(M_V, [0.0, 0.0, 1.0], integrator=Integrator(4.0, limit=3.0))
    parts = PointMass(M_V, [0.0, 0.0, 1.0], integrator=Integrator(4.0, limit=3.0))
    whole.advance(0.8, f)
    for _ in range(800):
        parts.advance(1e-3, f)
    assert whole.integral == 3.0 and parts.integral == 3.0
    np.testing.assert_allclose(whole.p, parts.p, rtol=0, atol=1e-13)
    np.testing.assert_allclose(whole.v, parts.v, rtol=0, atol=1e-13)
    # the unclamped law reaches I = 3 at t_c = ln(4.905 / 1.905) / 4
    t_c = np.log((M_L * G / M_V) / (M_L * G / M_V - 3.0)) / 4.0
    probe = PointMass(M_V, [0.0, 0.0, 1.0], integrator=Integrator(4.0, limit=3.0))
    probe.advance(t_c * (1 - 1e-9), f)
    assert probe.integral == pytest.approx(3.0, abs=1e-8) and probe.integral < 3.0
    assert parts.accel()[2] == pytest.approx(3.0 - M_L * G / M_V, abs=1e-12)  # saturated: residual sag


# -- cables and equilibrium -------------------------------------------------------------------

def test_cable_is_one_sided() -> None:
    cab = CableArrays(np.array([1.0, 1.0, 1.0, 1.0]), np.full(4, 100.0), np.full(4, 2.0))
    pl, vl = np.zeros(3), np.zeros(3)
    p = np.array([[0, 0, 1.01], [0, 0, 1.01], [0, 0, 0.99], [0, 0, 0.99]], dtype=float)
    v = np.array([[0, 0, 0.1], [0, 0, -1.0], [0, 0, 5.0], [0, 0, -5.0]], dtype=float)
    t, f = cable_forces(p, v, pl, vl, cab)
    # taut and lengthening: spring + damper; taut but shortening fast: the damper does not push;
    # slack (L < L0), even lengthening fast: nothing at all
    np.testing.assert_allclose(t, [100 * 0.01 + 2 * 0.1, 0.0, 0.0, 0.0], rtol=1e-12, atol=0)
    np.testing.assert_allclose(f[0], [0.0, 0.0, -t[0]], rtol=1e-12)
    assert np.all(f[1:] == 0.0)


def test_hover_equilibrium_symmetric_and_not() -> None:
    cab = CableParams(L0)
    eq = hover_equilibrium(SQUARE, M_L, cab)
    np.testing.assert_allclose(eq.payload_p[:2], [0.0, 0.0], rtol=0, atol=1e-12)  # below the centroid
    np.testing.assert_allclose(eq.tensions, eq.tensions[0], rtol=1e-12)
    np.testing.assert_allclose(eq.forces.sum(axis=0), [0.0, 0.0, -M_L * G], rtol=0, atol=1e-14)
    np.testing.assert_allclose(eq.stretch, eq.tensions / cab.stiffness, rtol=1e-12)
    np.testing.assert_allclose(eq.feedforward_masses().sum(), M_L, rtol=1e-12)
    # an uneven formation (heights, spacing) with two kinds of cable
    rng = np.random.default_rng(3)
    p = SQUARE + rng.uniform(-0.15, 0.15, SQUARE.shape)
    cables = [CableParams(0.5), CableParams(0.7, stiffness=80.0), CableParams(0.6), CableParams(0.55, stiffness=300.0)]
    eq = hover_equilibrium(p, M_L, cables)
    np.testing.assert_allclose(eq.forces.sum(axis=0), [0.0, 0.0, -M_L * G], rtol=0, atol=1e-14)
    length = np.linalg.norm(p - eq.payload_p, axis=1)
    k = np.array([c.stiffness for c in cables])
    l0 = np.array([c.rest_length for c in cables])
    np.testing.assert_allclose(eq.tensions, k * np.maximum(length - l0, 0.0), rtol=1e-12, atol=1e-15)
    assert eq.payload_p[2] < p[:, 2].min()


def test_world_at_equilibrium_starts_and_stays_at_rest() -> None:
    for options in ("hold", "feedforward"):
        if options == "hold":
            w, eq = PayloadWorld.at_equilibrium(_square(), M_L, CableParams(L0))
            w.command_all(eq.hold_accel(w.masses))
        else:
            eq = hover_equilibrium(SQUARE, M_L, CableParams(L0))
            vs = [PointMass(M_V, p, feedforward_mass=mff) for p, mff in zip(SQUARE, eq.feedforward_masses())]
            w = PayloadWorld(vs, M_L, eq.payload_p, None, CableParams(L0))
            u = -eq.forces / (M_V + eq.feedforward_masses())[:, None]
            u[:, 2] = 0.0
            w.command_all(u)
        np.testing.assert_allclose(w.implied_disturbance, eq.forces / M_V, rtol=1e-12)
        for _ in range(100):
            w.advance(H)
        np.testing.assert_allclose(w.p, SQUARE, rtol=0, atol=1e-10)
        np.testing.assert_allclose(w.payload_p, eq.payload_p, rtol=0, atol=1e-10)
        np.testing.assert_allclose(w.tensions, eq.tensions, rtol=1e-8)
        assert -w.cable_forces[:, 2].sum() == pytest.approx(M_L * G, rel=1e-8)
        assert np.all(w.slack_events == 0) and np.all(w.taut)


def test_hovering_vehicles_carry_the_payload_weight() -> None:
    """Four point masses holding their positions with a PD law (and the nominal quarter share as
    feed-forward) lift a payload released on unstretched cables: after settling (3 s), the vertical
    components of the tensions sum to the payload's weight (within 1 %). The PD leaves the vehicles
    pulled inwards by (horizontal pull) / kp: Eq. 17 has no integral action either."""
    kp, kd = 6.0, 5.0
    w = PayloadWorld(_square(feedforward_mass=M_L / 4), M_L, [0.0, 0.0, 1.0 - np.sqrt(L0**2 - 2 * 0.35**2)],
                     None, CableParams(L0))
    assert np.all(w.tensions == 0.0)
    for _ in range(300):
        w.command_all(-kp * (w.p - SQUARE) - kd * w.v)
        w.advance(H)
    lift = -w.cable_forces[:, 2].sum()
    assert lift == pytest.approx(M_L * G, rel=0.01)
    assert np.abs(w.payload_v).max() < 1e-3 and np.abs(w.v).max() < 1e-3 and np.all(w.taut)


# -- slack ------------------------------------------------------------------------------------

def test_slack_cables_exert_no_force() -> None:
    """A payload thrown up between the vehicles (every cable shorter than its rest length) is in
    exact free fall, and the hovering vehicles feel nothing."""
    p0, v0 = np.array([0.0, 0.0, 1.2]), np.array([0.1, -0.05, 0.8])
    w = PayloadWorld(_square(), M_L, p0, v0, CableParams(L0))
    for k in range(1, 31):
        w.advance(H)
        t = k * H
        assert np.all(np.linalg.norm(SQUARE - w.payload_p, axis=1) < L0)
        free_fall = p0 + v0 * t + 0.5 * t * t * np.array([0.0, 0.0, -G])
        np.testing.assert_allclose(w.payload_p, free_fall, rtol=0, atol=1e-13)
        np.testing.assert_allclose(w.payload_accel, [0.0, 0.0, -G], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(w.p, SQUARE)
    np.testing.assert_array_equal(w.v, np.zeros((4, 3)))
    assert np.all(w.tensions == 0.0) and np.all(w.implied_disturbance == 0.0) and not w.taut.any()
    assert np.all(w.slack_events == 0)  # never taut, so never a taut->slack transition


def test_diving_vehicles_slacken_the_cables_and_the_events_are_counted() -> None:
    w, eq = PayloadWorld.at_equilibrium(_square(), M_L, CableParams(L0))
    hold = eq.hold_accel(w.masses)
    w.command_all(hold)
    w.advance(H)
    w.command_all(hold + [0.0, 0.0, -2.0 * G])  # dive faster than the payload can fall
    w.advance(H)
    assert np.all(w.slack_events == 1) and not w.taut.any()
    for _ in range(4):
        w.advance(H)
        np.testing.assert_allclose(w.payload_accel, [0.0, 0.0, -G], rtol=0, atol=1e-12)  # free fall
        np.testing.assert_array_equal(w.implied_disturbance, np.zeros((4, 3)))
    w.command_all(hold + [0.0, 0.0, 3.0 * G])  # climb: the cables snap taut again, and bounce
    taut = []
    for _ in range(10):
        w.advance(H)
        taut.append(w.taut.copy())
    assert np.any(taut, axis=0).all()
    assert np.all(w.slack_events == w.slack_events[0]) and w.slack_events[0] >= 2  # symmetric snaps


# -- energy and damping -----------------------------------------------------------------------

def test_undamped_world_conserves_energy() -> None:
    """c = 0. (a) Vehicles under constant thrust (the equilibrium's hold commands: gravity and the
    equilibrium pull compensated, no feedback), payload swinging, cables taut: position Verlet keeps
    the energy within 0.6 % of the initial kinetic energy over 2 s at 1 kHz, and the error falls as
    dt^2. (b) u = 0 (motors compensate only the vehicles' weight): the formation collapses onto the
    falling payload, with many slack events; the energy stays within 1 % of the initial KE."""
    cab = CableParams(L0, damping=0.0)
    vl0 = np.array([0.05, 0.0, 0.02])
    errors = []
    for substep in (1e-3, 5e-4):
        w, eq = PayloadWorld.at_equilibrium(_square(), M_L, cab, substep)
        w = PayloadWorld(w.vehicles, M_L, eq.payload_p, vl0, cab, substep)
        w.command_all(eq.hold_accel(w.masses))
        e0 = _energy(w, cab.stiffness, eq.forces)
        dev = []
        for _ in range(200):
            w.advance(H)
            dev.append(_energy(w, cab.stiffness, eq.forces) - e0)
        assert np.all(w.slack_events == 0)
        errors.append(np.abs(dev).max() / (0.5 * M_L * vl0 @ vl0))
    assert errors[0] < 0.006
    assert 3.5 < errors[0] / errors[1] < 4.5  # second order

    vl0 = np.array([0.4, 0.0, 0.1])
    eq = hover_equilibrium(SQUARE, M_L, cab)
    w = PayloadWorld(_square(), M_L, eq.payload_p, vl0, cab)
    e0 = _energy(w, cab.stiffness)
    assert w.energy() == pytest.approx(e0, rel=1e-14)
    dev = []
    for _ in range(200):
        w.advance(H)
        dev.append(_energy(w, cab.stiffness) - e0)
    assert w.slack_events.min() > 10
    assert np.abs(dev).max() < 0.01 * 0.5 * M_L * vl0 @ vl0


def _prony_rate(x: np.ndarray, step: float) -> tuple[float, float]:
    """Decay rate [1/s] and frequency [rad/s] of a sampled damped sinusoid, from the least-squares
    fit of x[n+1] = a1 x[n] + a2 x[n-1] (exact for one mode: a2 = -exp(-2 sigma step))."""
    a = np.linalg.lstsq(np.stack([x[1:-1], x[:-2]], axis=1), x[2:], rcond=None)[0]
    sigma = -np.log(-a[1]) / (2 * step)
    omega = np.arccos(a[0] / (2 * np.exp(-sigma * step))) / step
    return sigma, omega


def test_damped_cable_oscillation_decays_at_the_predicted_rate() -> None:
    """One vehicle (feed-forward = the payload mass) and a payload hanging below it: the stretch
    oscillates about m_L g / k with the two-body mode mu = m_v m_L / (m_v + m_L), rate c / (2 mu)."""
    cab = CableParams(L0, stiffness=200.0, damping=0.3)
    mu = M_V * M_L / (M_V + M_L)
    x_eq = M_L * G / cab.stiffness
    veh = PointMass(M_V, [0.0, 0.0, 1.0], feedforward_mass=M_L)
    dt = 1e-3
    w = PayloadWorld([veh], M_L, [0.0, 0.0, 1.0 - L0 - x_eq - 2e-4], None, cab, dt)
    x = []
    for _ in range(300):
        w.advance(dt)
        x.append(w.p[0, 2] - w.payload_p[2] - L0 - x_eq)
        assert w.taut[0]
    sigma, omega = _prony_rate(np.array(x), dt)
    zeta_w = cab.damping / (2 * mu)
    omega_d = np.sqrt(cab.stiffness / mu - zeta_w**2)
    assert sigma == pytest.approx(zeta_w, rel=0.02)  # measured: +1.5 % (the explicit damper)
    assert omega == pytest.approx(omega_d, rel=0.01)
    # the scheme's own linear map predicts both to round-off
    w2, c = cab.stiffness / mu, cab.damping / mu
    amp = np.array([[1 - w2 * dt * dt / 2, dt - w2 * dt**3 / 4 - c * dt * dt / 2],
                    [-w2 * dt, 1 - w2 * dt * dt / 2 - c * dt]])
    lam = np.log(np.linalg.eigvals(amp)[0]) / dt
    assert sigma == pytest.approx(-lam.real, rel=1e-6)
    assert omega == pytest.approx(abs(lam.imag), rel=1e-6)


# -- the payload as the paper's disturbance ---------------------------------------------------

def test_implied_disturbance_is_the_mean_cable_force_per_mass() -> None:
    rng = np.random.default_rng(11)
    eq = hover_equilibrium(SQUARE, M_L, CableParams(L0))
    a = PayloadWorld(_square(), M_L, eq.payload_p, [0.2, 0.1, 0.0], CableParams(L0))
    b = PayloadWorld(_square(), M_L, eq.payload_p, [0.2, 0.1, 0.0], CableParams(L0))
    hold = eq.hold_accel(a.masses)
    for _ in range(30):
        u = hold + rng.normal(0.0, 1.0, (4, 3))
        a.command_all(u)
        b.command_all(u)
        a.advance(H)
        forces = []
        for _ in range(10):  # the same period, one substep at a time
            b.advance(1e-3)
            forces.append(b.cable_forces)
        np.testing.assert_array_equal(a.p, b.p)  # splitting a period changes nothing
        np.testing.assert_allclose(a.implied_disturbance, np.mean(forces, axis=0) / M_V, rtol=0, atol=1e-14)
        # a plain point mass: the mean acceleration is u + d exactly (Eq. 5)
        np.testing.assert_allclose(a.accel, u + a.implied_disturbance, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.model_residual, a.implied_disturbance, rtol=0, atol=1e-12)


def test_sag_without_and_with_the_inner_loop_remedies() -> None:
    """One 30 g vehicle carries 15 g alone (a 4.9 m/s^2 pull) under a PD position hold
    (Eq. 17 has no integral action either): it sags by pull / kp; the feed-forward mass and the
    integrator remove the sag; an integrator clamped below the pull leaves (pull - limit) / kp."""
    kp, kd, pull = 10.0, 6.0, M_L * G / M_V
    ref = np.array([0.0, 0.0, 1.0])
    cases = {
        "none": ({}, pull / kp),
        "feedforward": ({"feedforward_mass": M_L}, 0.0),
        "integrator": ({"integrator": Integrator(5.0, limit=8.0)}, 0.0),
        "clamped": ({"integrator": Integrator(5.0, limit=3.0)}, (pull - 3.0) / kp),
    }
    for name, (options, sag) in cases.items():
        veh = PointMass(M_V, ref, **options)
        w = PayloadWorld([veh], M_L, ref - [0.0, 0.0, L0 + M_L * G / 200.0], None, CableParams(L0))
        for _ in range(400):
            w.command_all(-kp * (w.p - ref) - kd * w.v)
            w.advance(H)
        assert ref[2] - w.p[0, 2] == pytest.approx(sag, abs=2e-3 * pull / kp), name
        np.testing.assert_allclose(w.implied_disturbance[0], [0.0, 0.0, -pull], rtol=0, atol=1e-3 * pull)


def test_a_quadrotor_carries_its_payload_in_the_same_world() -> None:
    """The world drives plant.quadrotor.Quadrotor through the same Vehicle interface: one Crazyflie
    with the payload's mass as feed-forward holds a payload hanging straight below it."""
    quadrotor = pytest.importorskip("plant.quadrotor")
    ref = np.array([0.0, 0.0, 1.0])
    q = quadrotor.Quadrotor(quadrotor.QuadrotorParams(feedforward_mass=M_L), ref)
    assert isinstance(q, Vehicle)
    w = PayloadWorld([q], M_L, ref - [0.0, 0.0, L0 + M_L * G / 200.0], None, CableParams(L0))
    for _ in range(100):
        w.command_all(-10.0 * (w.p - ref) - 6.0 * w.v)
        w.advance(H)
    np.testing.assert_allclose(w.p[0], ref, rtol=0, atol=1e-6)
    assert -w.cable_forces[0, 2] == pytest.approx(M_L * G, rel=0.01)
    np.testing.assert_allclose(w.implied_disturbance, w.cable_forces / q.mass, rtol=1e-6)
    assert w.slack_events[0] == 0


# -- bookkeeping ------------------------------------------------------------------------------

def test_runs_are_deterministic() -> None:
    def run() -> PayloadWorld:
        rng = np.random.default_rng(5)
        w, eq = PayloadWorld.at_equilibrium(_square(integrator=Integrator(2.0, limit=5.0)), M_L, CableParams(L0))
        for _ in range(50):
            w.command_all(rng.normal(0.0, 3.0, (4, 3)))
            w.advance(H)
        return w

    a, b = run(), run()
    for name in ("p", "v", "accel", "payload_p", "payload_v", "tensions", "implied_disturbance", "slack_events"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_rejects_what_it_cannot_integrate() -> None:
    with pytest.raises(ValueError, match="too long"):
        PayloadWorld(_square(), M_L, [0.0, 0.0, 0.4], None, CableParams(L0), substep=0.01)
    w = PayloadWorld(_square(), M_L, [0.0, 0.0, 0.4], None, CableParams(L0))
    with pytest.raises(ValueError, match="whole number"):
        w.advance(0.0105)
    with pytest.raises(ValueError, match="list of 4"):
        PayloadWorld(_square(), M_L, [0.0, 0.0, 0.4], None, [CableParams(L0)] * 3)
    with pytest.raises(ValueError):
        CableParams(L0, damping=-1.0)
    omega, _ = frequency_bound(np.full(4, M_V), M_L, CableArrays.of(CableParams(L0), 4))
    assert omega == pytest.approx(np.sqrt(8 * 200.0 / M_L))
