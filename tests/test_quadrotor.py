"""The 6-DOF quadrotor (plant/quadrotor.py): kinematics against Eq. 2-3, Eq. 4 and its saturation, the
integrator against an independent numpy reference and closed forms, rigid-body invariants, the inner
loop's step responses, the payload options, and the paper's Remark 1 measured at the plant level.

Run as a script to print the numbers quoted in docs/quadrotor.md::

    .venv/bin/python -m tests.test_quadrotor
"""

from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np
import pytest

from plant import double_integrator
from plant import quadrotor as qr
from plant.quadrotor import Quadrotor, QuadrotorParams, eq4

P = QuadrotorParams()
G = P.g


# ------------------------------------------------------------------------------------ helpers
def _eq2(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Eq. 2 transcribed from the paper."""
    cf, sf, ct, st, cp, sp = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    return np.array([
        [ct * cp, sf * st * cp - cf * sp, cf * st * cp + sf * sp],
        [ct * sp, sf * st * sp + cf * cp, cf * st * sp - sf * cp],
        [-st, sf * ct, cf * ct],
    ])


def step_response(params: QuadrotorParams, u: np.ndarray, duration: float = 4.0,
                  dt: float = 0.002) -> tuple[np.ndarray, np.ndarray, Quadrotor]:
    """Hover, then ``u`` from t = 0: the times and the mean accelerations over each ``dt``."""
    q = Quadrotor(params, [0.0, 0.0, 1.0])
    q.command(u)
    acc = []
    for _ in range(round(duration / dt)):
        q.advance(dt)
        acc.append(q.accel())
    return (np.arange(len(acc)) + 1) * dt, np.array(acc), q


def step_metrics(t: np.ndarray, acc: np.ndarray, u: np.ndarray) -> dict[str, float]:
    """Rise time (10-90 %), overshoot, and the times after which ``|a - u| <= tol |u|`` for good."""
    u = np.asarray(u, dtype=float)
    axis = int(np.argmax(np.abs(u)))
    y = acc[:, axis] / u[axis]
    err = np.linalg.norm(acc - u, axis=1) / np.linalg.norm(u)

    def settle(tol: float) -> float:
        out = np.nonzero(err > tol)[0]
        if not len(out):
            return 0.0
        return float(t[out[-1] + 1]) if out[-1] + 1 < len(t) else math.inf

    return {"t10": float(t[np.argmax(y >= 0.1)]), "t90": float(t[np.argmax(y >= 0.9)]),
            "overshoot": float(y.max() - 1.0), "settle10": settle(0.10), "settle5": settle(0.05),
            "settle2": settle(0.02), "cross": float(np.abs(np.delete(acc, axis, axis=1)).max())}


def remark1(ufun: Callable[[float], list[float]], duration: float = 10.0, h: float = 0.01,
            params: QuadrotorParams = P) -> dict[str, float]:
    """The quadrotor and the double integrator ``p'' = u`` (exact ZOH) under the same command ``u(t_k)``
    held over each ``h``, from the same hover state: position and velocity gaps, acceleration error."""
    q = Quadrotor(params, [0.0, 0.0, 1.0])
    p, v = np.array([0.0, 0.0, 1.0]), np.zeros(3)
    zero = np.zeros(3)
    gaps, aerr = [], []
    for k in range(round(duration / h)):
        u = np.asarray(ufun(k * h), dtype=float)
        q.command(u)
        q.advance(h)
        p, v, _ = double_integrator.step(p, v, u, zero, zero, h)
        gaps.append(float(np.linalg.norm(q.p - p)))
        aerr.append(float(np.linalg.norm(q.accel() - u)))
    return {"gap_end": gaps[-1], "gap_max": max(gaps), "vgap_end": float(np.linalg.norm(q.v - v)),
            "a_rms": float(np.sqrt(np.mean(np.square(aerr)))), "eq4_saturated": q.saturation.eq4 / q.saturation.ticks}


_W = 2.0 * math.pi * 0.2
REMARK1_GENTLE: dict[str, tuple[Callable[[float], list[float]], float]] = {
    # name: (u(t), bound on the position gap after 10 s [m])
    "x: 0.5 sin(2 pi 0.2 t)": (lambda t: [0.5 * math.sin(_W * t), 0.0, 0.0], 0.10),
    "xyz: 0.5 sin(2 pi 0.2 t) each": (lambda t: [0.5 * math.sin(_W * t)] * 3, 0.15),
}
REMARK1_AGGRESSIVE: dict[str, tuple[Callable[[float], list[float]], float]] = {
    # name: (u(t), lower bound on the position gap after 10 s [m])
    "x: 10 m/s^2 step": (lambda t: [10.0, 0.0, 0.0], 100.0),
    "x: 2 sin(2 pi 3 t)": (lambda t: [2.0 * math.sin(2.0 * math.pi * 3.0 * t), 0.0, 0.0], 2.0),
}


# -------------------------------------------------------------------------------- parameters
def test_default_parameters_are_valid_and_those_of_a_crazyflie() -> None:
    assert P.validate() == []
    assert 0.027 <= P.mass <= 0.034
    assert P.arm_length == 0.046
    np.testing.assert_allclose(P.inertia, [1.66e-5, 1.67e-5, 2.93e-5], rtol=0.003, atol=0)
    assert P.control_rate == 500.0
    # hover needs about 63 % of the four motors' thrust: room left for attitude control
    assert 0.5 < P.mass * G / P.collective_thrust_max < 0.7


@pytest.mark.parametrize(("change", "field"), [
    ({"mass": 0.0}, "mass"),
    ({"mass": float("nan")}, "mass"),
    ({"inertia": (1e-5, 1e-5)}, "inertia"),
    ({"inertia": (1e-5, 1e-5, 3e-5)}, "inertia"),  # Ixx + Iyy < Izz: no rigid body has it
    ({"tilt_max": math.pi / 2}, "tilt_max"),
    ({"motor_thrust_max": 0.05}, "motor_thrust_max"),  # cannot hover
    ({"feedforward_mass": 0.02}, "motor_thrust_max"),  # cannot hover with the payload share
    ({"feedforward_mass": -0.001}, "feedforward_mass"),
    ({"control_rate": 300.0}, "control_rate"),  # 3.33... ms is not whole nanoseconds
    ({"physics_substeps": 3}, "physics_substeps"),  # 2 ms / 3
    ({"physics_substeps": 0}, "physics_substeps"),
    ({"motor_tau": 0.0}, "motor_tau"),  # ideal motors: the firmware's rate D gain is unstable
    ({"rate_kd": (0.0, -1.0, 0.0)}, "rate_kd"),
    ({"z_integrator_gain": -1.0}, "z_integrator_gain"),
])
def test_validate_names_the_bad_field(change: dict, field: str) -> None:
    bad = QuadrotorParams(**change)
    problems = bad.validate()
    assert field in [f for f, _ in problems], problems
    assert all(";" in msg for _, msg in problems)  # "<what is wrong>; <how to fix it>"
    with pytest.raises(ValueError, match=field):
        Quadrotor(bad, [0, 0, 0])


def test_ideal_motors_are_fine_with_a_gentler_rate_d_gain() -> None:
    kd = P.rate_kd[0] * 0.5
    ok = QuadrotorParams(motor_tau=0.0, rate_kd=(kd, kd, 0.0))
    assert ok.validate() == []
    q = Quadrotor(ok, [0, 0, 1])
    q.command([1.0, 0.5, 0.0])
    for _ in range(200):
        q.advance(0.01)
    assert q.saturation.motors == 0
    np.testing.assert_allclose(q.accel(), [1.0, 0.5, 0.0], rtol=0, atol=0.05)


# ------------------------------------------------------------------------------- kinematics
def test_quaternion_rotation_is_eq2_and_euler_round_trips() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        roll, yaw = rng.uniform(-math.pi, math.pi, 2)
        pitch = rng.uniform(-1.5, 1.5)
        q = qr.quaternion_from_euler(roll, pitch, yaw)
        assert abs(np.linalg.norm(q) - 1.0) < 1e-15
        np.testing.assert_allclose(qr.rotation_matrix(q), _eq2(roll, pitch, yaw), rtol=0, atol=1e-15)
        np.testing.assert_allclose(qr.euler_from_quaternion(q), [roll, pitch, yaw], rtol=0, atol=1e-9)
        np.testing.assert_allclose(qr.euler_from_quaternion(-q), [roll, pitch, yaw], rtol=0, atol=1e-9)


def test_eq3_relates_body_rates_and_euler_rates_along_a_flight() -> None:
    # the Euler angles' finite differences along a free tumble equal Eq. 3's inverse applied to omega
    q = Quadrotor(P, [0, 0, 0], omega0=[0.7, -0.4, 1.1])
    q.command_attitude(0.0, 0.0, 0.0, 0.0)
    h = 1e-4
    for _ in range(50):
        q.advance(0.01)
        e0, om = np.array(q.euler()), q.omega
        q.advance(h)
        e1 = np.array(q.euler())
        fd = np.array([qr.wrap_angle(d) for d in (e1 - e0)]) / h
        mid = qr.euler_rates_from_body_rates(*(0.5 * (e0 + e1))[:2], 0.5 * (om + q.omega))
        np.testing.assert_allclose(fd, mid, rtol=0, atol=1e-6)
        back = qr.body_rates_from_euler_rates(e0[0], e0[1], qr.euler_rates_from_body_rates(e0[0], e0[1], om))
        np.testing.assert_allclose(back, om, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------------------- Eq. 4
def test_eq4_inverts_to_the_commanded_acceleration() -> None:
    rng = np.random.default_rng(1)
    m = 0.031
    for _ in range(500):
        u = rng.uniform(-2.5, 2.5, 3)
        yaw = rng.uniform(-math.pi, math.pi)
        thrust, roll, pitch, sat = eq4(u, yaw, m, G, math.radians(35), 10.0)
        assert not sat
        got = thrust * _eq2(roll, pitch, yaw)[:, 2] / m - np.array([0, 0, G])
        np.testing.assert_allclose(got, u, rtol=0, atol=1e-12)
        # the paper's form of the thrust, T = m (u_z + g) / (cos(roll) cos(pitch)), and of the roll
        assert thrust == pytest.approx(m * (u[2] + G) / (math.cos(roll) * math.cos(pitch)), rel=1e-12)
        assert roll == pytest.approx(math.asin(m * (u[0] * math.sin(yaw) - u[1] * math.cos(yaw)) / thrust), abs=1e-12)


def test_eq4_pitch_needs_the_plus_sign_not_the_papers_minus() -> None:
    # the paper prints tan(pitch) = (u_x cos psi - u_y sin psi) / (u_z + g); Eq. 2 requires "+"
    u, yaw, m = np.array([0.3, 0.8, 0.0]), 1.0, 0.03
    _, _, pitch, _ = eq4(u, yaw, m, G, 0.5, 10.0)
    assert pitch == pytest.approx(math.atan((u[0] * math.cos(yaw) + u[1] * math.sin(yaw)) / G), abs=1e-15)
    assert abs(pitch - math.atan((u[0] * math.cos(yaw) - u[1] * math.sin(yaw)) / G)) > 0.05


def test_eq4_hover_and_zero_thrust() -> None:
    assert eq4(np.zeros(3), 0.7, 0.03, G, 0.3, 1.0) == (pytest.approx(0.03 * G, rel=1e-15), 0.0, 0.0, False)
    assert eq4(np.array([1.0, 0.0, -G]), 0.0, 0.03, G, 0.3, 1.0) == (0.0, 0.0, 0.0, True)  # a_z <= 0


def test_eq4_tilt_saturation_keeps_the_vertical_part_and_the_direction() -> None:
    m, tilt = 0.03, math.radians(20)
    u = np.array([8.0, -6.0, 1.0])
    thrust, roll, pitch, sat = eq4(u, 0.4, m, G, tilt, 1.0)
    assert sat
    f = thrust * _eq2(roll, pitch, 0.4)[:, 2] / m
    assert math.acos(f[2] / np.linalg.norm(f)) == pytest.approx(tilt, abs=1e-12)
    assert f[2] == pytest.approx(u[2] + G, rel=1e-12)
    np.testing.assert_allclose(f[:2] / np.linalg.norm(f[:2]), u[:2] / np.linalg.norm(u[:2]), rtol=0, atol=1e-12)


def test_eq4_thrust_saturation_gives_priority_to_the_vertical() -> None:
    m, tmax = 0.03, 0.45
    # room for the vertical part: the horizontal part shrinks until |T| = tmax
    u = np.array([6.0, 0.0, 5.0])
    thrust, roll, pitch, sat = eq4(u, 0.0, m, G, math.radians(40), tmax)
    f = thrust * _eq2(roll, pitch, 0.0)[:, 2] / m
    assert sat and thrust == pytest.approx(tmax, rel=1e-12)
    assert f[2] == pytest.approx(u[2] + G, rel=1e-12) and f[0] > 0
    # not even for the vertical part: straight up at tmax
    thrust, roll, pitch, sat = eq4(np.array([1.0, 1.0, 8.0]), 0.0, m, G, math.radians(40), tmax)
    assert sat and (thrust, roll, pitch) == (pytest.approx(tmax, rel=1e-12), 0.0, 0.0)


# ------------------------------------------------------------------------------------- mixer
def test_mixer_inverts_the_wrench_and_caps_thrust_before_torque() -> None:
    rng = np.random.default_rng(2)
    for _ in range(200):
        f = rng.uniform(0.0, P.motor_thrust_max, 4)
        thrust, tau = qr.wrench(f, P)
        got, sat = qr.mix(thrust, tau, P)
        np.testing.assert_allclose(got, f, rtol=0, atol=1e-15)
        assert not sat
    # too much thrust: all four lowered by the same excess, so the torque survives
    thrust, tau = 4 * 0.11, np.array([1e-4, -2e-4, 5e-5])
    got, sat = qr.mix(thrust, tau, P)
    assert sat and got.max() == pytest.approx(P.motor_thrust_max, rel=1e-15)
    np.testing.assert_allclose(qr.wrench(got, P)[1], tau, rtol=1e-12, atol=0)


# ------------------------------------------------------------------------------ integration
def test_hover_is_an_equilibrium() -> None:
    q = Quadrotor(P, [0.3, -1.0, 1.0], yaw0=2.0)
    for _ in range(500):
        q.advance(0.01)
    np.testing.assert_allclose(q.p, [0.3, -1.0, 1.0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(q.v, 0.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(q.motor_thrusts, P.mass * G / 4, rtol=1e-12, atol=0)
    np.testing.assert_allclose(q.euler(), [0.0, 0.0, 2.0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(q.rotor_speeds, math.sqrt(P.mass * G / 4 / P.thrust_coeff), rtol=1e-12, atol=0)
    assert q.saturation.ticks == 2500 and q.saturation.eq4 == q.saturation.motors == 0 and not q.saturated


def test_integrator_matches_an_independent_numpy_reference() -> None:
    # the motor commands of each control period, replayed through newton_euler + the motor ODE with
    # plain RK4 at a 10x finer step, give the same flight
    q = Quadrotor(P, [0.0, 0.0, 1.0], omega0=[0.2, -0.1, 0.3])
    f_ext = np.array([0.002, -0.001, -0.003])
    x = np.concatenate([q.p, q.v, q.quaternion, q.omega])
    f = q.motor_thrusts
    hc, n = 0.002, 10
    h = hc / n

    def rhs(x: np.ndarray, f: np.ndarray, fc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return qr.newton_euler(0.0, x, np.concatenate([f, f_ext]), P), (fc - f) / P.motor_tau

    for k in range(250):
        q.command([2.0 * math.sin(3.0 * k * hc), -1.0, 0.5 * math.cos(5.0 * k * hc)], yaw=0.5 * math.sin(k * hc))
        q.advance(hc, f_ext)
        fc = q.motor_commands
        for _ in range(n):
            k1 = rhs(x, f, fc)
            k2 = rhs(x + 0.5 * h * k1[0], f + 0.5 * h * k1[1], fc)
            k3 = rhs(x + 0.5 * h * k2[0], f + 0.5 * h * k2[1], fc)
            k4 = rhs(x + h * k3[0], f + h * k3[1], fc)
            x = x + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            f = f + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
            x[6:10] /= np.linalg.norm(x[6:10])
    assert q.saturation.motors == 0 and np.abs(q.p - [0, 0, 1]).max() > 0.05  # it did fly
    np.testing.assert_allclose(q.p, x[0:3], rtol=0, atol=1e-10)
    np.testing.assert_allclose(q.v, x[3:6], rtol=0, atol=1e-10)
    np.testing.assert_allclose(q.quaternion, x[6:10], rtol=0, atol=1e-10)
    np.testing.assert_allclose(q.omega, x[10:13], rtol=0, atol=1e-10)
    np.testing.assert_allclose(q.motor_thrusts, f, rtol=0, atol=1e-12)


def test_quaternion_stays_unit_and_rotation_orthonormal_over_60_s() -> None:
    q = Quadrotor(P, [0, 0, 1])
    eye = np.eye(3)
    for k in range(6000):
        t = 0.01 * k
        q.command([1.5 * math.sin(0.9 * t), 1.5 * math.cos(0.7 * t), 0.5 * math.sin(1.3 * t)], yaw=0.4 * t)
        q.advance(0.01)
        if k % 10 == 0:
            assert abs(np.linalg.norm(q.quaternion) - 1.0) <= 1e-12
            r = q.rotation
            assert np.abs(r.T @ r - eye).max() <= 1e-12
    assert abs(np.linalg.norm(q.quaternion) - 1.0) <= 1e-12


def test_torque_free_rotation_conserves_world_angular_momentum_and_energy() -> None:
    inertia = np.array(P.inertia)
    q = Quadrotor(P, [0, 0, 0], omega0=[3.0, -2.0, 5.0])
    q.command_attitude(0.0, 0.0, 0.0, 0.0)  # motors off: four equal thrusts decaying, zero torque
    momentum0 = q.rotation @ (inertia * q.omega)
    energy0 = 0.5 * q.omega @ (inertia * q.omega)
    for _ in range(300):
        q.advance(0.01)
        momentum = q.rotation @ (inertia * q.omega)
        assert np.linalg.norm(momentum - momentum0) <= 1e-9 * np.linalg.norm(momentum0)
        assert abs(0.5 * q.omega @ (inertia * q.omega) - energy0) <= 1e-9 * energy0
    assert np.abs(q.omega - [3.0, -2.0, 5.0]).max() > 0.1  # it did precess


def test_motors_off_is_free_fall_after_the_motor_lag() -> None:
    z0, tau = 10.0, P.motor_tau
    q = Quadrotor(P, [0.0, 0.0, z0], v0=[0.5, 0.0, 0.0])
    q.command_attitude(0.0, 0.0, 0.0, 0.0)
    for k in range(1, 201):
        q.advance(0.01)
        t = 0.01 * k
        # hover thrust decaying as exp(-t / tau): z'' = g exp(-t / tau) - g
        vz = G * tau * (1.0 - math.exp(-t / tau)) - G * t
        z = z0 + G * tau * (t - tau * (1.0 - math.exp(-t / tau))) - 0.5 * G * t * t
        np.testing.assert_allclose(q.p, [0.5 * t, 0.0, z], rtol=0, atol=1e-9)
        np.testing.assert_allclose(q.v, [0.5, 0.0, vz], rtol=0, atol=1e-9)
    np.testing.assert_allclose(q.accel(), [0.0, 0.0, -G], rtol=0, atol=1e-9)  # exp(-2 / 0.072) ~ 1e-12
    np.testing.assert_array_equal(q.motor_commands, 0.0)


def test_advance_lands_on_the_same_schedule_whatever_the_chunks() -> None:
    def fly(chunks: list[float]) -> Quadrotor:
        q = Quadrotor(P, [0, 0, 1])
        q.command([1.0, -0.5, 0.2], yaw=0.3)
        for dt in chunks:
            q.advance(dt, f_ext=[0.0, 0.0, -0.001])
        return q

    a = fly([0.01] * 100)
    b = fly([0.003] * 333 + [0.001])  # spans ending on the 1 ms physics grid: bit for bit
    c = fly([0.0037] * 270 + [0.001])  # spans ending between grid points: the same flight to 2e-13
    assert a.t == b.t == c.t == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_array_equal(np.concatenate([a.p, a.v, a.quaternion]), np.concatenate([b.p, b.v, b.quaternion]))
    np.testing.assert_allclose(c.p, a.p, rtol=0, atol=1e-11)
    np.testing.assert_allclose(c.v, a.v, rtol=0, atol=1e-11)
    assert a.saturation.ticks == c.saturation.ticks == 500


def test_accel_is_the_mean_acceleration_of_the_last_span() -> None:
    q = Quadrotor(P, [0, 0, 1])
    np.testing.assert_array_equal(q.accel(), 0.0)
    q.command([0.8, 0.0, -0.3])
    for dt in (0.01, 0.037, 0.0005):
        v0 = q.v
        q.advance(dt)
        np.testing.assert_allclose(q.accel(), (q.v - v0) / dt, rtol=1e-9, atol=1e-12)


def test_commands_and_spans_are_checked() -> None:
    q = Quadrotor(P, [0, 0, 1])
    with pytest.raises(ValueError):
        q.command([0.0, float("nan"), 0.0])
    with pytest.raises(ValueError):
        q.command_attitude(-0.1, 0.0, 0.0, 0.0)
    for dt in (0.0, -0.01, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            q.advance(dt)
    with pytest.raises(ValueError):
        q.advance(0.01, f_ext=[0.0, 0.0, float("nan")])
    with pytest.raises(ValueError):
        Quadrotor(P, [0.0, float("inf"), 0.0])


# ------------------------------------------------------------------------------ inner loop
def test_horizontal_step_reaches_the_commanded_acceleration() -> None:
    u = np.array([1.0, 0.0, 0.0])
    t, acc, q = step_response(P, u, duration=3.5)
    m = step_metrics(t, acc, u)
    # measured (docs/quadrotor.md): t90 0.294 s, overshoot 5.7 %, within 10 % from 0.294 s,
    # within 5 % from 1.364 s (the attitude PID's integral leaves a slow tail), within 2 % from 3.14 s
    assert m["t90"] <= 0.32
    assert 0.0 < m["overshoot"] <= 0.07
    assert m["settle10"] <= 0.32
    assert m["settle5"] <= 1.5
    assert m["settle2"] <= 3.3
    assert m["cross"] <= 0.05  # the vertical bump while tilting (Eq. 4 sets T for the final tilt)
    assert q.saturation.eq4 == q.saturation.motors == 0


def test_vertical_step_is_the_motor_lag() -> None:
    # level flight: Eq. 4 sets the new thrust at once, the motors reach it as 1 - exp(-t / tau)
    u, hc, tau = np.array([0.0, 0.0, 1.5]), 0.002, P.motor_tau
    t, acc, _ = step_response(P, u, duration=0.5, dt=hc)
    expected = u[2] * (1.0 - tau / hc * (np.exp(-(t - hc) / tau) - np.exp(-t / tau)))  # mean over each span
    np.testing.assert_allclose(acc[:, 2], expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(acc[:, :2], 0.0, rtol=0, atol=1e-12)


def test_attitude_setpoint_is_tracked() -> None:
    q = Quadrotor(P, [0, 0, 1])
    q.command_attitude(P.mass * G, 0.1, -0.05, 0.0)
    for _ in range(300):
        q.advance(0.01)
    # the attitude PID's integral leaves a slow tail: 2 % above the setpoint after 3 s
    np.testing.assert_allclose(q.euler(), [0.1, -0.05, 0.0], rtol=0, atol=0.003)
    assert q.attitude_setpoint[:3] == (P.mass * G, 0.1, -0.05)


@pytest.mark.parametrize(("yaw0", "yaw1"), [(0.0, 0.5), (3.0, -3.0)])
def test_yaw_tracking_takes_the_short_way(yaw0: float, yaw1: float) -> None:
    q = Quadrotor(P, [0, 0, 1], yaw0=yaw0)
    q.command([0.0, 0.0, 0.0], yaw=yaw1)
    path = []
    for _ in range(400):
        q.advance(0.01)
        path.append(qr.wrap_angle(q.euler()[2] - yaw0))
    step = qr.wrap_angle(yaw1 - yaw0)
    assert abs(qr.wrap_angle(q.euler()[2] - yaw1)) <= 0.03 * abs(step)  # measured 2 % after 4 s
    assert min(np.sign(step) * np.array(path)) >= -1e-6  # never the long way round
    assert max(abs(p) for p in path) <= 1.1 * abs(step)  # overshoot 6.6 %
    np.testing.assert_allclose(q.euler()[:2], 0.0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(q.p, [0, 0, 1], rtol=0, atol=1e-9)
    assert q.saturation.motors == 0


def test_yaw_rate_command_integrates_into_the_yaw_setpoint() -> None:
    q = Quadrotor(P, [0, 0, 1])
    q.command_attitude(P.mass * G, 0.0, 0.0, 0.5)
    for _ in range(1000):
        q.advance(0.01)
    assert q.omega[2] == pytest.approx(0.5, rel=0.02)  # measured 0.5037 rad/s after 10 s
    assert qr.wrap_angle(q.attitude_setpoint[3] - 5.0) == pytest.approx(0.0, abs=1e-9)


def test_saturation_is_counted() -> None:
    q = Quadrotor(P, [0, 0, 1])
    q.command([10.0, 0.0, 0.0])  # needs 45 deg of tilt, 20 deg allowed
    for _ in range(300):
        q.advance(0.01)
    assert q.saturated and q.saturation.eq4 == q.saturation.ticks == 1500
    assert q.euler()[1] == pytest.approx(P.tilt_max, abs=0.01)
    assert q.accel()[0] == pytest.approx(G * math.tan(P.tilt_max), rel=0.03)


# ----------------------------------------------------------------------------------- payload
def test_feedforward_mass_carries_a_payload_share_like_no_payload() -> None:
    # a payload share moving with the vehicle pulls f_ext = -m_ff (u + g e_z); with the share in
    # Eq. 4 the loaded vehicle flies exactly as the unloaded one does
    m_ff = 0.008
    loaded = Quadrotor(QuadrotorParams(feedforward_mass=m_ff), [0, 0, 1])
    empty = Quadrotor(P, [0, 0, 1])
    for k in range(300):
        u = np.array([0.6 * math.sin(0.02 * k), 0.3, -0.2 * math.cos(0.03 * k)])
        for quad in (loaded, empty):
            quad.command(u, yaw=0.2)
        loaded.advance(0.01, f_ext=-m_ff * (loaded.accel() + [0.0, 0.0, G]) if k else [0.0, 0.0, -m_ff * G])
        empty.advance(0.01)
    np.testing.assert_allclose(loaded.p, empty.p, rtol=0, atol=0.005)  # measured 2e-3 m (f_ext lags a span)
    # hovering against its weight alone, the share holds altitude; without it the vehicle sinks
    for params, sink in ((QuadrotorParams(feedforward_mass=m_ff), 0.0), (P, -m_ff * G / P.mass)):
        q = Quadrotor(params, [0, 0, 1])
        for _ in range(100):
            q.advance(0.01, f_ext=[0.0, 0.0, -m_ff * G])
        np.testing.assert_allclose(q.accel(), [0.0, 0.0, sink], rtol=0, atol=1e-9)


def test_z_integrator_is_off_by_default_and_removes_a_vertical_pull() -> None:
    pull = np.array([0.0, 0.0, -0.004 * G])  # 4 g of unmodelled payload
    q = Quadrotor(P, [0, 0, 1])
    for _ in range(300):
        q.advance(0.01, f_ext=pull)
    assert q.z_integrator == 0.0 and q.accel()[2] == pytest.approx(pull[2] / P.mass, rel=1e-9)

    params = QuadrotorParams(z_integrator_gain=5.0, z_integrator_limit=2.0)
    q = Quadrotor(params, [0, 0, 1])
    for _ in range(300):
        q.advance(0.01, f_ext=pull)
    assert abs(q.accel()[2]) <= 1e-3  # measured: 2e-9 m/s^2 after 3 s
    assert q.z_integrator == pytest.approx(-pull[2] / P.mass, rel=1e-2)
    # a pull beyond the anti-windup bound: the correction stops at the bound and unwinds quickly
    for _ in range(300):
        q.advance(0.01, f_ext=3 * pull)
    assert q.z_integrator == pytest.approx(2.0, rel=1e-12)
    for _ in range(150):
        q.advance(0.01)
    assert abs(q.accel()[2]) <= 0.05 and abs(q.z_integrator) <= 0.05


# --------------------------------------------------------------------------------- Remark 1
@pytest.mark.parametrize("name", list(REMARK1_GENTLE))
def test_remark1_gentle_commands_fly_like_the_double_integrator(name: str) -> None:
    ufun, bound = REMARK1_GENTLE[name]
    r = remark1(ufun)
    assert r["gap_end"] <= bound and r["eq4_saturated"] == 0.0, r


@pytest.mark.parametrize("name", list(REMARK1_AGGRESSIVE))
def test_remark1_breaks_down_for_aggressive_commands(name: str) -> None:
    ufun, bound = REMARK1_AGGRESSIVE[name]
    r = remark1(ufun)
    assert r["gap_end"] >= bound, r


# ------------------------------------------------------------------------ printed numbers
def _report() -> None:
    """Print the numbers docs/quadrotor.md quotes."""
    print("step responses (mean acceleration over 2 ms; times from the step) [s]:")
    for tau in (P.motor_tau, 0.03, 0.01):
        params = QuadrotorParams(motor_tau=tau)
        for u in ([1.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 0.0, 1.0]):
            t, acc, q = step_response(params, np.array(u), duration=4.0)
            m = step_metrics(t, acc, np.array(u))
            print(f"  motor_tau {tau:5.3f}  u {u}: t10 {m['t10']:.3f}  t90 {m['t90']:.3f}  overshoot "
                  f"{100 * m['overshoot']:.1f} %  within 10/5/2 % from {m['settle10']:.3f}/{m['settle5']:.3f}/"
                  f"{m['settle2']:.3f}  max off-axis {m['cross']:.3f} m/s^2  saturated ticks {q.saturation.eq4}"
                  f"/{q.saturation.motors}")
    print("horizontal frequency response (u_x = 0.5 sin(2 pi f t) at 100 Hz; fit of a_x over the second half):")
    for f in (0.2, 0.5, 1.0, 3.0):
        w, duration = 2.0 * math.pi * f, 20.0
        q = Quadrotor(P, [0, 0, 1])
        t, ax, az = [], [], []
        for k in range(round(duration * 100)):
            q.command([0.5 * math.sin(w * 0.01 * k), 0.0, 0.0])
            q.advance(0.01)
            t.append(0.01 * k + 0.005)  # the mean over [t_k, t_k + h] is centred at t_k + h/2
            ax.append(q.accel()[0])
            az.append(q.accel()[2])
        tt = np.array(t)
        keep = tt > duration / 2
        basis = np.column_stack([np.sin(w * tt[keep]), np.cos(w * tt[keep]), np.ones(keep.sum())])
        c = np.linalg.lstsq(basis, np.array(ax)[keep], rcond=None)[0]
        phase = math.atan2(c[1], c[0])
        print(f"  {f:3.1f} Hz: gain {math.hypot(c[0], c[1]) / 0.5:.3f}  phase {phase:.3f} rad (a delay of "
              f"{-phase / w:.3f} s)  mean a_z {np.mean(np.array(az)[keep]):.2g} m/s^2")
    print("Remark 1 (quadrotor vs p'' = u, same ZOH command at 100 Hz, 10 s):")
    for name, (ufun, _) in {**REMARK1_GENTLE, **REMARK1_AGGRESSIVE}.items():
        r = remark1(ufun)
        print(f"  {name:32s} |dp| end {r['gap_end']:.4g} m  max {r['gap_max']:.4g} m  |dv| end "
              f"{r['vgap_end']:.4g} m/s  rms |a - u| {r['a_rms']:.4g} m/s^2  Eq. 4 saturated "
              f"{100 * r['eq4_saturated']:.0f} % of ticks")
    print("yaw steps (hover, yaw command stepped at t = 0):")
    for yaw1 in (0.5, 1.0):
        q = Quadrotor(P, [0, 0, 1])
        q.command([0.0, 0.0, 0.0], yaw=yaw1)
        path = []
        for _ in range(400):
            q.advance(0.01)
            path.append(q.euler()[2])
        t = (np.arange(len(path)) + 1) * 0.01
        err = np.abs(np.array(path) - yaw1) / yaw1
        out = np.nonzero(err > 0.05)[0]
        print(f"  {yaw1} rad: t90 {t[np.argmax(err <= 0.1)]:.2f} s  overshoot {100 * (max(path) / yaw1 - 1):.1f} %  "
              f"within 5 % from {t[out[-1] + 1]:.2f} s  error at 4 s {100 * err[-1]:.1f} %  |dp| "
              f"{np.linalg.norm(q.p - [0, 0, 1]):.3g} m  motor-saturated ticks {q.saturation.motors}")
    q = Quadrotor(P, [0, 0, 1])
    q.command_attitude(P.mass * G, 0.0, 0.0, 0.5)
    for _ in range(1000):
        q.advance(0.01)
    print(f"  yaw rate 0.5 rad/s asked: {q.omega[2]:.4f} rad/s after 10 s")

    def wild(params: QuadrotorParams) -> np.ndarray:
        q = Quadrotor(params, [0, 0, 1])
        for k in range(1000):
            t = 0.01 * k
            w = 2.0 * math.pi * t
            q.command([5.0 * math.sin(w), 2.5 * math.cos(w), 1.5 * math.sin(w)], yaw=0.3 * t)
            q.advance(0.01)
        return q.p

    ref = wild(QuadrotorParams(physics_substeps=20))
    for sub in (1, 2, 4):
        gap = np.abs(wild(QuadrotorParams(physics_substeps=sub)) - ref).max()
        print(f"physics step: {sub} RK4 step(s) per control period vs 20: max |dp| after 10 s of 1 Hz, "
              f"5 m/s^2 commands = {gap:.2g} m")
    for sub in (1, 2, 4):
        params = QuadrotorParams(physics_substeps=sub)
        q = Quadrotor(params, [0, 0, 1])
        start = time.process_time()
        for k in range(2500):
            q.command([0.5 * math.sin(_W * 0.01 * k), 0.0, 0.0])
            q.advance(0.01)
        print(f"speed: physics_substeps {sub} ({sub * params.control_rate:.0f} Hz): 25 s simulated at 100 Hz "
              f"commands in {time.process_time() - start:.2f} s CPU")


if __name__ == "__main__":
    _report()
