"""A Crazyflie 2.1-class quadrotor: the Newton-Euler rigid body (Eq. 1-3), Eq. 4 and a firmware-like
cascaded PID inner loop at 500 Hz. Pure Python/numpy: no I/O, no clock, no randomness.

It exists to *test* the paper's Remark 1 (a quadrotor closed by its inner loop is approximately the
double integrator ``p'' = u``), not to assume it. ``docs/quadrotor.md`` has the derivations, the
parameter sources and the measured inner-loop and Remark 1 numbers.

Frames, units and signs
    World frame: x, y horizontal, z up; gravity is ``-g e_z`` [m, m/s, m/s^2].
    Body frame: origin at the centre of mass, x forward, y left, z up (along the thrust).
    Attitude: a unit quaternion ``q = (w, x, y, z)``, scalar first (the project's one quaternion
    order), that rotates body vectors into the world: ``v_world = R(q) v_body``. ``R(q)`` equals
    Eq. 2's ``R_e^b(eta)`` for the Z-Y-X Euler angles ``eta = (roll phi, pitch theta, yaw psi)``
    [rad]: positive pitch tilts the thrust towards +x (nose down), positive roll towards -y.
    Body rates ``omega = (p, q, r)`` [rad/s; body frame]; Euler rates follow Eq. 3.

Rigid body (Eq. 1), with the total thrust ``T`` and torque ``tau`` of the four motors::

    p' = v
    m v' = T R(q) e_z - m g e_z + f_ext            (f_ext [N; world]: cable pull, disturbance)
    q'  = 1/2 q (x) (0, omega)                       (quaternion product)
    I omega' = -omega x I omega + tau                (I = diag(Ixx, Iyy, Izz) [kg m^2; body])

No aerodynamic drag, no rotor gyroscopic torque, no ground: the vehicle flies from wherever it
starts (as the double integrator does).

Motors and mixer (X configuration, numbering and signs of crazyflie-firmware's force-torque mixer):
M1 front-right (+a, -a), M2 back-right (-a, -a), M3 back-left (-a, +a), M4 front-left (+a, +a) in
body (x, y), ``a = arm_length / sqrt(2)``::

    T = f1 + f2 + f3 + f4
    tau_x = a (-f1 - f2 + f3 + f4),   tau_y = a (-f1 + f2 + f3 - f4),   tau_z = c (-f1 + f2 - f3 + f4)

with ``c`` the drag-torque-to-thrust ratio [m]. Each motor's thrust is limited to ``[0, f_max]``; a
command above ``f_max`` lowers all four by the excess first (the firmware's ``powerDistributionCap``:
torque before thrust). An optional first-order lag ``tau_m`` moves each thrust towards its command,
``f' = (f_cmd - f) / tau_m``, integrated exactly.

Inner loop, at ``control_rate`` (500 Hz, the firmware's ``ATTITUDE_RATE``), on ideal measurements:
    1. setpoint: from :meth:`Quadrotor.command` (Eq. 4: ``u`` -> ``T, phi_d, theta_d`` for the given
       yaw ``psi_d``) or from :meth:`Quadrotor.command_attitude` (``T, phi_d, theta_d`` and a yaw
       rate integrated into ``psi_d``, as the firmware's yaw "velocity" mode does);
    2. attitude PID on the Euler-angle errors -> Euler-rate setpoint -> body-rate setpoint by Eq. 3;
    3. body-rate PID -> torque ``tau`` [N m], clamped; 4. mixer -> four motor thrust commands.
The PIDs are the firmware's ``pid.c`` (derivative on the measurement, integral clamped) with its
default gains converted to SI (see :data:`FIRMWARE_GAINS_SI`). A commanded thrust of exactly zero
switches the motors off and resets the PIDs, as the firmware does.

Payload options (both for :meth:`Quadrotor.command` only): ``feedforward_mass`` ``m_ff`` adds the
vehicle's share of a payload to the mass Eq. 4 uses, ``T = (m + m_ff)(u_z + g)/(cos phi cos theta)``;
``z_integrator_gain`` ``k_z > 0`` integrates, at every tick, the gap between the ``u_z`` asked for
over the last period and the mean vertical acceleration achieved over it, ``I += (u_z - a_z) h``
(``I`` is the vertical velocity lost [m/s]), and adds ``k_z I`` to ``u_z``, clamped to
``z_integrator_limit`` (anti-windup). It restores ``p_z'' = u_z`` under a steady pull, not the
velocity lost while it converged (the outer law sees that as a velocity error).

Integration: fixed-step classical RK4 on the 13 states ``(p, v, q, omega)`` at
``control_rate * physics_substeps`` (default 500 Hz x 2 = 1 kHz), motor thrusts known in closed form
at every stage, the quaternion renormalised after every step. Time is kept in integer nanoseconds,
so :meth:`Quadrotor.advance` with any ``dt > 0`` lands on the same controller schedule (a span that
ends between grid points integrates a shorter last step).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from collections.abc import Sequence
from typing import Callable, Literal

import numpy as np

DEG = math.pi / 180.0
"""One degree [rad]."""

# ------------------------------------------------------------------ firmware gains, converted to SI
# crazyflie-firmware, src/platform/interface/platform_defaults_cf2.h: PID_*_K{P,I,D} and
# PID_*_INTEGRATION_LIMIT; src/modules/src/power_distribution_quadrotor.c: the legacy mixer
# (m_i = thrust -/+ roll/2 -/+ pitch/2 -/+ yaw); the battery-compensated motor command maps
# linearly to thrust, 65535 -> THRUST_MAX per motor.
#   attitude PID: error [deg] -> rate setpoint [deg/s]: gains are unit-free, used as they are (1/s).
#   rate PID: error [deg/s] -> motor-command units; one command unit of the roll (pitch) output is
#     a torque 2 (L/sqrt 2)(THRUST_MAX/65535) [N m] (+/- half a unit on each of the four motors at
#     moment arm L/sqrt 2), one unit of yaw output 4 c THRUST_MAX/65535 [N m].
_FW_THRUST_MAX = 0.1125  # [N per motor] THRUST_MAX (CF 2.1 propellers)
_FW_ARM = 0.046  # [m] ARM_LENGTH
_FW_THRUST2TORQUE = 0.005964552  # [m] THRUST2TORQUE (Förster 2015)
_N_PER_UNIT = _FW_THRUST_MAX / 65535.0  # [N] per motor-command unit
_ROLL_NM_PER_UNIT = 2.0 * (_FW_ARM / math.sqrt(2.0)) * _N_PER_UNIT  # [N m]
_YAW_NM_PER_UNIT = 4.0 * _FW_THRUST2TORQUE * _N_PER_UNIT  # [N m]


def _rate_gain(k_fw: float, nm_per_unit: float) -> float:
    """A firmware rate gain [units per deg/s (per deg, per deg/s^2)] in SI [N m per rad/s (...)]."""
    return k_fw / DEG * nm_per_unit


FIRMWARE_GAINS_SI: dict[str, tuple[float, float, float]] = {
    # attitude (angle) PID, per axis (roll, pitch, yaw): firmware (6, 3, 0), (6, 3, 0), (6, 1, 0.35)
    "att_kp": (6.0, 6.0, 6.0),  # [1/s]
    "att_ki": (3.0, 3.0, 1.0),  # [1/s^2]
    "att_kd": (0.0, 0.0, 0.35),  # [-]
    "att_ilimit": (20.0 * DEG, 20.0 * DEG, 360.0 * DEG),  # [rad s]: firmware 20, 20, 360 deg s
    # body-rate PID: firmware roll/pitch (250, 500, 2.5), yaw (120, 16.7, 0)
    "rate_kp": (_rate_gain(250.0, _ROLL_NM_PER_UNIT), _rate_gain(250.0, _ROLL_NM_PER_UNIT),
                _rate_gain(120.0, _YAW_NM_PER_UNIT)),  # [N m s/rad]
    "rate_ki": (_rate_gain(500.0, _ROLL_NM_PER_UNIT), _rate_gain(500.0, _ROLL_NM_PER_UNIT),
                _rate_gain(16.7, _YAW_NM_PER_UNIT)),  # [N m/rad]
    "rate_kd": (_rate_gain(2.5, _ROLL_NM_PER_UNIT), _rate_gain(2.5, _ROLL_NM_PER_UNIT), 0.0),  # [N m s^2/rad]
    "rate_ilimit": (33.3 * DEG, 33.3 * DEG, 166.7 * DEG),  # [rad]: firmware 33.3, 33.3, 166.7 deg
    # the rate PID's output is saturated to a signed 16-bit command (attitude_pid_controller.c)
    "torque_max": (32767 * _ROLL_NM_PER_UNIT, 32767 * _ROLL_NM_PER_UNIT, 32767 * _YAW_NM_PER_UNIT),  # [N m]
}
"""crazyflie-firmware's default attitude and rate PID gains (platform_defaults_cf2.h) in SI units."""

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class QuadrotorParams:
    """Vehicle, motor and inner-loop parameters; defaults are a Crazyflie 2.1 (sources beside each).

    Construct with keyword arguments to change any of them; :meth:`validate` lists what is wrong.
    """

    mass: float = 0.029
    """Vehicle mass [kg]. crazyflie-firmware CF_MASS (platform_defaults_cf2.h); Bitcraze lists 27 g
    bare, the paper "about 25 g"; decks and battery variants span 0.027-0.034 kg."""
    inertia: Vec3 = (16.571710e-6, 16.655602e-6, 29.261652e-6)
    """Principal moments of inertia (Ixx, Iyy, Izz) [kg m^2; body frame]. Förster (2015), System
    identification of the Crazyflie 2.0 nano quadrocopter, ETH Zurich (also Crazyswarm2's sim)."""
    arm_length: float = 0.046
    """Centre to motor axis [m]. crazyflie-firmware ARM_LENGTH; 92 mm motor to motor (paper Sect. 5.1)."""
    motor_thrust_max: float = 0.1125
    """Per-motor thrust limit ``f_max`` [N]. crazyflie-firmware THRUST_MAX for the CF 2.1 propellers
    (the firmware's full-scale command; a scaling constant, not a measured stall thrust)."""
    thrust_to_torque: float = 0.005964552
    """Rotor drag torque per unit thrust ``c`` [m]. crazyflie-firmware THRUST2TORQUE (Förster 2015)."""
    thrust_coeff: float = 2.3e-8
    """Rotor thrust coefficient ``k_f`` [N/(rad/s)^2], ``f = k_f Omega^2``; only used to report rotor
    speeds. RotorPy crazyflie_params.py (14.5 g at 2500 rad/s). The drag coefficient is
    ``k_m = c k_f`` [N m/(rad/s)^2]."""
    motor_tau: float = 0.072
    """First-order motor time constant [s]; 0 = ideal motors. Eschmann, Albani & Loianno (2024),
    Data-driven system identification of quadrotors subject to motor delays, arXiv:2404.07837
    (about 72 ms for the Crazyflie; RotorPy's crazyflie_params.py tau_m). With ideal motors the
    firmware's rate D gain is unstable at 500 Hz (:meth:`validate` says so)."""
    g: float = 9.81
    """Gravitational acceleration [m/s^2]."""
    tilt_max: float = 20.0 * DEG
    """Eq. 4's tilt limit [rad]: the angle between thrust and vertical. crazyflie-firmware's position
    controller limits roll and pitch to 20 deg (PID_VEL_ROLL_MAX, PID_VEL_PITCH_MAX)."""
    feedforward_mass: float = 0.0
    """Extra mass [kg] added to ``mass`` in Eq. 4 only (the vehicle's share of a payload); the
    physical mass stays ``mass``: ``T = (m + m_ff) |u + g e_z|``."""
    z_integrator_gain: float = 0.0
    """Gain ``k_z`` [1/s] of the vertical acceleration-error integrator; 0 = off (default)."""
    z_integrator_limit: float = 2.0
    """Anti-windup bound [m/s^2] on the integrator's correction ``|k_z I|`` of ``u_z``."""
    integrator_axes: str = "z"
    """``"z"``: the integrator acts on the vertical axis only; ``"xyz"``: on every axis, each with
    its own integral, gain and bound (the Crazyflie's velocity PIDs integrate x, y and z)."""
    control_rate: float = 500.0
    """Inner-loop rate [Hz]. crazyflie-firmware ATTITUDE_RATE (RATE_500_HZ)."""
    physics_substeps: int = 2
    """RK4 steps per control period (physics at ``control_rate * physics_substeps`` Hz)."""
    att_kp: Vec3 = FIRMWARE_GAINS_SI["att_kp"]
    """Attitude PID proportional gains (roll, pitch, yaw) [1/s]."""
    att_ki: Vec3 = FIRMWARE_GAINS_SI["att_ki"]
    """Attitude PID integral gains [1/s^2]."""
    att_kd: Vec3 = FIRMWARE_GAINS_SI["att_kd"]
    """Attitude PID derivative gains (on the measured angle) [-]."""
    att_ilimit: Vec3 = FIRMWARE_GAINS_SI["att_ilimit"]
    """Attitude PID integral clamp, on the integrated error [rad s]."""
    rate_kp: Vec3 = FIRMWARE_GAINS_SI["rate_kp"]
    """Rate PID proportional gains (p, q, r) [N m s/rad]."""
    rate_ki: Vec3 = FIRMWARE_GAINS_SI["rate_ki"]
    """Rate PID integral gains [N m/rad]."""
    rate_kd: Vec3 = FIRMWARE_GAINS_SI["rate_kd"]
    """Rate PID derivative gains (on the measured rate) [N m s^2/rad]."""
    rate_ilimit: Vec3 = FIRMWARE_GAINS_SI["rate_ilimit"]
    """Rate PID integral clamp, on the integrated error [rad]."""
    torque_max: Vec3 = FIRMWARE_GAINS_SI["torque_max"]
    """Rate PID output clamp (x, y, z) [N m]: the firmware's 16-bit command limit."""

    @property
    def collective_thrust_max(self) -> float:
        """``4 f_max`` [N]: Eq. 4's thrust limit."""
        return 4.0 * self.motor_thrust_max

    @property
    def drag_coeff(self) -> float:
        """``k_m = c k_f`` [N m/(rad/s)^2]."""
        return self.thrust_to_torque * self.thrust_coeff

    @property
    def control_period_ns(self) -> int:
        """The control period [ns] (validated to be a whole number of nanoseconds)."""
        return round(1e9 / self.control_rate)

    def validate(self) -> list[tuple[str, str]]:
        """Every problem as ``(field, "<what is wrong>; <how to fix it>")``; empty when valid."""
        out: list[tuple[str, str]] = []
        for f in fields(self):
            val = getattr(self, f.name)
            if f.name == "integrator_axes":  # the one text field, checked below
                continue
            vals = val if isinstance(val, tuple) else (val,)
            if isinstance(val, tuple) and len(val) != 3:
                out.append((f.name, f"has {len(val)} values; give three (roll/x, pitch/y, yaw/z)"))
            if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in vals):
                out.append((f.name, f"is {val!r}; use finite numbers"))
        if out:
            return out

        def positive(name: str, hint: str) -> None:
            if not getattr(self, name) > 0:
                out.append((name, f"is {getattr(self, name)}; {hint}"))

        positive("mass", "use the vehicle's mass in kg, e.g. 0.029")
        positive("arm_length", "use the centre-to-motor distance in m, e.g. 0.046")
        positive("motor_thrust_max", "use the per-motor thrust limit in N, e.g. 0.1125")
        positive("thrust_to_torque", "use the rotor drag torque per newton of thrust in m, e.g. 0.006")
        positive("thrust_coeff", "use k_f in N/(rad/s)^2, e.g. 2.3e-8")
        positive("g", "use 9.81 m/s^2")
        positive("control_rate", "use the inner-loop rate in Hz, e.g. 500")
        if any(x <= 0 for x in self.inertia):
            out.append(("inertia", f"is {self.inertia}; every principal moment must be > 0 kg m^2"))
        else:
            ix, iy, iz = self.inertia
            if ix + iy < iz or iy + iz < ix or iz + ix < iy:
                out.append(("inertia", f"is {self.inertia}, which breaks the triangle inequality of a rigid "
                                       "body; check the moments (e.g. Ixx + Iyy >= Izz)"))
        if self.motor_tau < 0:
            out.append(("motor_tau", f"is {self.motor_tau}; use 0 (ideal motors) or a time constant > 0 s"))
        if not 0 < self.tilt_max < math.pi / 2:
            out.append(("tilt_max", f"is {self.tilt_max} rad; use an angle in (0, pi/2), e.g. 20 deg = 0.349"))
        if self.feedforward_mass < 0:
            out.append(("feedforward_mass", f"is {self.feedforward_mass}; use 0 or the payload share in kg"))
        if self.z_integrator_gain < 0:
            out.append(("z_integrator_gain", f"is {self.z_integrator_gain}; use 0 (off) or a gain > 0 1/s"))
        if self.integrator_axes not in ("z", "xyz"):
            out.append(("integrator_axes", f"is {self.integrator_axes!r}; use 'z' or 'xyz'"))
        if self.z_integrator_limit < 0:
            out.append(("z_integrator_limit", f"is {self.z_integrator_limit}; use a bound >= 0 m/s^2"))
        if any(x <= 0 for x in self.torque_max):
            out.append(("torque_max", f"is {self.torque_max}; every torque limit must be > 0 N m"))
        for name in ("att_kp", "att_ki", "att_kd", "att_ilimit", "rate_kp", "rate_ki", "rate_kd", "rate_ilimit"):
            if any(x < 0 for x in getattr(self, name)):
                out.append((name, f"is {getattr(self, name)}; gains and limits must be >= 0"))
        if not isinstance(self.physics_substeps, int) or self.physics_substeps < 1:
            out.append(("physics_substeps", f"is {self.physics_substeps!r}; use a whole number >= 1, e.g. 2"))
        if self.control_rate > 0:
            period = 1e9 / self.control_rate
            if abs(period - round(period)) > 1e-6:
                out.append(("control_rate", f"is {self.control_rate} Hz, whose period is not a whole number of "
                                            "nanoseconds; use a divisor of 1e9, e.g. 500"))
            elif isinstance(self.physics_substeps, int) and self.physics_substeps >= 1 \
                    and round(period) % self.physics_substeps:
                out.append(("physics_substeps", f"is {self.physics_substeps}, which does not divide the control "
                                                f"period of {round(period)} ns; use a divisor, e.g. 2 or 4"))
        if self.motor_tau == 0 and self.control_rate > 0 and not any(x <= 0 for x in self.inertia):
            # ideal motors: the sampled rate loop I w+ = I w + h (kp e - kd (w - w-) / h) has a root
            # beyond z = -1 (Jury's condition at z = -1) when kp h / I + 2 kd / I >= 2
            h = 1.0 / self.control_rate
            jury = [(self.rate_kp[i] * h + 2.0 * self.rate_kd[i]) / self.inertia[i] for i in range(3)]
            bad = [f"{axis} ({j:.3g})" for axis, j in zip("xyz", jury) if j >= 2.0]
            if bad:
                out.append(("motor_tau", f"is 0 (ideal motors), with which the rate loop oscillates unstably at "
                                         f"{self.control_rate} Hz about {', '.join(bad)}: rate_kp h / I + "
                                         "2 rate_kd / I >= 2; set motor_tau > 0 (1 ms is enough) or lower rate_kd"))
        weight = (self.mass + max(self.feedforward_mass, 0.0)) * self.g
        if self.mass > 0 and self.g > 0 and self.motor_thrust_max > 0 and weight >= self.collective_thrust_max:
            out.append(("motor_thrust_max", f"is {self.motor_thrust_max} N: four motors give "
                                            f"{self.collective_thrust_max:.4g} N, not more than the "
                                            f"{weight:.4g} N that Eq. 4 needs to hover (mass + feedforward_mass); "
                                            "raise it or lower the mass"))
        return out


# ------------------------------------------------------------------------------ pure kinematics
def rotation_matrix(q: np.ndarray) -> np.ndarray:
    """``R(q)`` (3, 3) of a unit quaternion ``(w, x, y, z)``: body vectors into the world frame."""
    w, x, y, z = (float(c) for c in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def quaternion_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """The unit quaternion ``(w, x, y, z)`` of Z-Y-X Euler angles [rad]: ``q = q_z(yaw) q_y(pitch) q_x(roll)``,
    so that ``R(q)`` is Eq. 2's ``R_e^b``."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return np.array([
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ])


def euler_from_quaternion(q: np.ndarray) -> tuple[float, float, float]:
    """Z-Y-X Euler angles ``(roll, pitch, yaw)`` [rad] of a unit quaternion ``(w, x, y, z)``, read off
    Eq. 2: ``roll = atan2(R32, R33)``, ``pitch = -asin(R31)``, ``yaw = atan2(R21, R11)``; roll and yaw
    in (-pi, pi], pitch in [-pi/2, pi/2]."""
    w, x, y, z = (float(c) for c in q)
    return _euler(w, x, y, z)


def _euler(w: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    s = 2.0 * (w * y - x * z)
    s = 1.0 if s > 1.0 else -1.0 if s < -1.0 else s
    return (math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y)), math.asin(s),
            math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))


def body_rates_from_euler_rates(roll: float, pitch: float, euler_rates: np.ndarray) -> np.ndarray:
    """Eq. 3: ``(p, q, r)`` [rad/s; body] from ``(roll', pitch', yaw')`` at the given roll and pitch."""
    dr, dp, dy = (float(c) for c in euler_rates)
    sr, cr, sp, cp = math.sin(roll), math.cos(roll), math.sin(pitch), math.cos(pitch)
    return np.array([dr - sp * dy, cr * dp + sr * cp * dy, -sr * dp + cr * cp * dy])


def euler_rates_from_body_rates(roll: float, pitch: float, omega: np.ndarray) -> np.ndarray:
    """The inverse of Eq. 3 (singular at pitch = +/-pi/2)."""
    p, q, r = (float(c) for c in omega)
    sr, cr, tp, cp = math.sin(roll), math.cos(roll), math.tan(pitch), math.cos(pitch)
    return np.array([p + (q * sr + r * cr) * tp, q * cr - r * sr, (q * sr + r * cr) / cp])


def wrap_angle(a: float) -> float:
    """``a`` wrapped to [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


# ------------------------------------------------------------------------------------- Eq. 4
def eq4(u: np.ndarray | Sequence[float], yaw: float, mass: float, g: float, tilt_max: float,
        thrust_max: float) -> tuple[float, float, float, bool]:
    """Eq. 4 with saturation: the thrust and attitude that give the world acceleration ``u``.

    Args:
        u: desired acceleration ``(u_x, u_y, u_z)`` [m/s^2; world frame, z up]; ``u = 0`` is hover.
        yaw: the desired yaw ``psi`` [rad].
        mass: the mass Eq. 4 uses [kg] (vehicle + feed-forward share of a payload).
        g: [m/s^2]. tilt_max: largest angle between thrust and vertical [rad], in (0, pi/2).
        thrust_max: largest collective thrust [N].
    Returns:
        ``(T [N], roll [rad], pitch [rad], saturated)``. With ``a = (u_x, u_y, u_z + g)``::

            T = m |a|,   roll = asin((a_x sin psi - a_y cos psi) / |a|),
            pitch = atan2(a_x cos psi + a_y sin psi, a_z)

        so that ``T R(roll, pitch, psi) e_z / m - g e_z = u`` (Eq. 2). The paper prints the pitch
        numerator as ``a_x cos psi - a_y sin psi``; the ``+`` here is what Eq. 2 requires (the test
        suite checks the inverse). Saturation keeps the vertical part first: a tilt above
        ``tilt_max`` shrinks the horizontal part of ``a`` to ``a_z tan(tilt_max)``; a thrust above
        ``thrust_max`` shrinks the horizontal part until ``m |a| = thrust_max`` and, if even the
        vertical part alone is too much, thrusts straight up at ``thrust_max``. With ``a_z <= 0``
        (falling faster than gravity) nothing can help: ``T = 0`` and level attitude.
    """
    ax, ay = float(u[0]), float(u[1])
    az = float(u[2]) + g
    if az <= 0.0:
        return 0.0, 0.0, 0.0, True
    saturated = False
    h2 = ax * ax + ay * ay
    hmax = az * math.tan(tilt_max)
    if h2 > hmax * hmax:
        s = hmax / math.sqrt(h2)
        ax, ay, h2, saturated = ax * s, ay * s, hmax * hmax, True
    amax = thrust_max / mass
    if h2 + az * az > amax * amax:
        saturated = True
        if az >= amax:
            ax, ay, az, h2 = 0.0, 0.0, amax, 0.0
        else:
            s = math.sqrt(amax * amax - az * az) / math.sqrt(h2)
            ax, ay, h2 = ax * s, ay * s, h2 * s * s
    norm = math.sqrt(h2 + az * az)
    sy, cy = math.sin(yaw), math.cos(yaw)
    sr = (ax * sy - ay * cy) / norm
    roll = math.asin(1.0 if sr > 1.0 else -1.0 if sr < -1.0 else sr)
    pitch = math.atan2(ax * cy + ay * sy, az)
    return mass * norm, roll, pitch, saturated


# ----------------------------------------------------------------------------- mixer, dynamics
def wrench(f: np.ndarray, params: QuadrotorParams) -> tuple[float, np.ndarray]:
    """Total thrust [N] and body torque (3,) [N m] of motor thrusts ``f = (f1, f2, f3, f4)`` [N]."""
    f1, f2, f3, f4 = (float(x) for x in f)
    a = params.arm_length / math.sqrt(2.0)
    c = params.thrust_to_torque
    return f1 + f2 + f3 + f4, np.array([a * (-f1 - f2 + f3 + f4), a * (-f1 + f2 + f3 - f4), c * (-f1 + f2 - f3 + f4)])


def mix(thrust: float, torque: np.ndarray, params: QuadrotorParams) -> tuple[np.ndarray, bool]:
    """Motor thrust commands (4,) [N] for a collective thrust [N] and body torque (3,) [N m], and
    whether a limit cut in: the exact inverse of :func:`wrench`, then the firmware's cap (every motor
    lowered by the excess of the largest over ``f_max``) and a clip to ``[0, f_max]``."""
    f = _mix(float(thrust), float(torque[0]), float(torque[1]), float(torque[2]),
             0.25 / (params.arm_length / math.sqrt(2.0)), 0.25 / params.thrust_to_torque, params.motor_thrust_max)
    return np.array(f[:4]), f[4]


def _mix(t: float, tx: float, ty: float, tz: float, ka: float, kc: float,
         fmax: float) -> tuple[float, float, float, float, bool]:
    base, rx, ry, rz = 0.25 * t, ka * tx, ka * ty, kc * tz
    f1 = base - rx - ry - rz
    f2 = base - rx + ry + rz
    f3 = base + rx + ry - rz
    f4 = base + rx - ry + rz
    top = max(f1, f2, f3, f4)
    sat = False
    if top > fmax:
        d = top - fmax
        f1, f2, f3, f4, sat = f1 - d, f2 - d, f3 - d, f4 - d, True
    if min(f1, f2, f3, f4) < 0.0:
        f1, f2, f3, f4, sat = max(f1, 0.0), max(f2, 0.0), max(f3, 0.0), max(f4, 0.0), True
    return f1, f2, f3, f4, sat


def newton_euler(t: float, x: np.ndarray, u: np.ndarray, params: QuadrotorParams) -> np.ndarray:
    """Eq. 1's right-hand side ``x'`` (13,) for ``x = (p, v, q, omega)`` and ``u = (f1..f4 [N],
    f_ext (3,) [N; world])``. The reference form (numpy, readable); :class:`Quadrotor` integrates
    the same equations in scalar arithmetic, which is several times faster on vectors this short."""
    v, q, om = x[3:6], x[6:10], x[10:13]
    thrust, tau = wrench(u[:4], params)
    inertia = np.array(params.inertia)
    acc = (thrust * rotation_matrix(q)[:, 2] + u[4:7]) / params.mass - np.array([0.0, 0.0, params.g])
    w, qv = q[0], q[1:]
    qdot = 0.5 * np.concatenate([[-qv @ om], w * om + np.cross(qv, om)])
    omdot = (tau - np.cross(om, inertia * om)) / inertia
    return np.concatenate([v, acc, qdot, omdot])


def _rigid_body_rhs(mass: float, inertia: Vec3) -> Callable[..., tuple[float, ...]]:
    """Eq. 1 in scalar arithmetic (the same equations as :func:`newton_euler`, several times faster on
    vectors this short): ``rhs(qw, qx, qy, qz, wx, wy, wz, T, tau_x, tau_y, tau_z)`` returns the thrust
    acceleration ``T R e_z / m`` (3 values, before gravity and ``f_ext``), ``q'`` (4) and ``omega'`` (3)."""
    ix, iy, iz = inertia
    inv_m = 1.0 / mass
    jx, jy, jz = 1.0 / ix, 1.0 / iy, 1.0 / iz
    cx, cy, cz = (iy - iz) * jx, (iz - ix) * jy, (ix - iy) * jz

    def rhs(qw: float, qx: float, qy: float, qz: float, wx: float, wy: float, wz: float,
            t: float, tx: float, ty: float, tz: float) -> tuple[float, ...]:
        tm = 2.0 * t * inv_m
        return (
            tm * (qx * qz + qw * qy), tm * (qy * qz - qw * qx), tm * (0.5 - qx * qx - qy * qy),
            -0.5 * (qx * wx + qy * wy + qz * wz), 0.5 * (qw * wx + qy * wz - qz * wy),
            0.5 * (qw * wy + qz * wx - qx * wz), 0.5 * (qw * wz + qx * wy - qy * wx),
            tx * jx + cx * wy * wz, ty * jy + cy * wz * wx, tz * jz + cz * wx * wy,
        )

    return rhs


# ----------------------------------------------------------------------------------- the plant
@dataclass
class SaturationCounts:
    """How often a limit cut in, counted in control ticks since construction."""

    ticks: int = 0
    """Control ticks run."""
    eq4: int = 0
    """Ticks where Eq. 4 saturated (tilt or collective thrust; also ``u_z + g <= 0``)."""
    motors: int = 0
    """Ticks where the mixer capped or clipped a motor."""


Mode = Literal["accel", "attitude"]


class Quadrotor:
    """One quadrotor with its 500 Hz inner loop; see the module docstring for the model.

    Not thread-safe; every call returns immediately (no I/O). Commands are held until the next one.
    """

    def __init__(self, params: QuadrotorParams, p0: np.ndarray, v0: np.ndarray | float = 0.0,
                 yaw0: float = 0.0, *, omega0: np.ndarray | float = 0.0) -> None:
        """Level at ``p0`` [m; world] with velocity ``v0`` [m/s; world], yaw ``yaw0`` [rad] and body rates
        ``omega0`` [rad/s; body], commanded to hover (``u = 0``, yaw ``yaw0``), each motor at a quarter
        of Eq. 4's hover thrust. The first control tick runs at ``t = 0``, in the first :meth:`advance`,
        on whatever command was given by then. Raises ``ValueError`` listing every problem of ``params``."""
        problems = params.validate()
        if problems:
            raise ValueError("invalid QuadrotorParams: " + "; ".join(f"{k}: {m}" for k, m in problems))
        p = np.broadcast_to(np.asarray(p0, dtype=float), (3,))
        v = np.broadcast_to(np.asarray(v0, dtype=float), (3,))
        self.params = params
        self.mass: float = params.mass
        """Physical mass [kg]."""
        q0 = quaternion_from_euler(0.0, 0.0, float(yaw0))
        w = np.broadcast_to(np.asarray(omega0, dtype=float), (3,))
        self._x = [*map(float, p), *map(float, v), *map(float, q0), *map(float, w)]
        if not all(math.isfinite(c) for c in self._x):
            raise ValueError(f"Quadrotor: p0 = {p0!r}, v0 = {v0!r}, yaw0 = {yaw0!r}, omega0 = {omega0!r}; "
                             "use finite numbers")
        # constants of the hot loop
        self._hc_ns = params.control_period_ns
        self._hp_ns = self._hc_ns // params.physics_substeps
        self._hc = self._hc_ns * 1e-9
        self._a = params.arm_length / math.sqrt(2.0)
        self._ka = 0.25 / self._a
        self._kc = 0.25 / params.thrust_to_torque
        self._c = params.thrust_to_torque
        self._g = params.g
        self._tau_m = params.motor_tau
        self._eq4_mass = params.mass + params.feedforward_mass
        self._thrust_max = params.collective_thrust_max
        self._rhs = _rigid_body_rhs(params.mass, params.inertia)
        self._decay: dict[int, tuple[float, float]] = {}
        # command and controller state
        self._mode: Mode = "accel"
        self._u = (0.0, 0.0, 0.0)
        self._yaw_cmd = float(yaw0)
        self._thrust_cmd = 0.0
        self._roll_cmd = 0.0
        self._pitch_cmd = 0.0
        self._yaw_rate_cmd = 0.0
        self._yaw_d = float(yaw0)
        self._setpoint = (0.0, 0.0, 0.0, float(yaw0))
        self._reset_pids()
        self._zi = 0.0
        self._vz_tick: float | None = None
        self._uz_tick = 0.0
        self._ii = (0.0, 0.0, 0.0)
        self._v_tick: tuple[float, float, float] | None = None
        self._u_tick = (0.0, 0.0, 0.0)
        self.saturation = SaturationCounts()
        self.saturated = False
        """Whether a limit cut in at the last control tick."""
        hover = min(0.25 * self._eq4_mass * params.g, params.motor_thrust_max)
        self._f = [hover] * 4
        self._fc = [hover] * 4
        self._t_ns = 0
        self._next_ctrl_ns = 0
        self._accel = (0.0, 0.0, 0.0)

    # -------------------------------------------------------------------------------- reading
    @property
    def t(self) -> float:
        """Simulated time since construction [s]."""
        return self._t_ns * 1e-9

    @property
    def p(self) -> np.ndarray:
        """Centre-of-mass position (3,) [m; world frame, z up]."""
        return np.array(self._x[0:3])

    @property
    def v(self) -> np.ndarray:
        """Centre-of-mass velocity (3,) [m/s; world frame]."""
        return np.array(self._x[3:6])

    def ground_contact(self, z: float) -> None:
        """The ground at height ``z`` [m] stops downward motion: the centre of mass is at least at
        ``z`` and a downward velocity is zeroed (a rigid, frictionless floor; attitude and body
        rates are the inner loop's); the vehicle climbs again as soon as its thrust lifts it."""
        if self._x[2] < z:
            self._x[2] = float(z)
        if self._x[5] < 0.0:
            self._x[5] = 0.0

    @property
    def quaternion(self) -> np.ndarray:
        """Attitude (4,) ``(w, x, y, z)``, unit, body to world."""
        return np.array(self._x[6:10])

    @property
    def omega(self) -> np.ndarray:
        """Body rates ``(p, q, r)`` (3,) [rad/s; body frame]."""
        return np.array(self._x[10:13])

    @property
    def rotation(self) -> np.ndarray:
        """``R`` (3, 3): body vectors into the world frame (Eq. 2)."""
        return rotation_matrix(self.quaternion)

    def euler(self) -> tuple[float, float, float]:
        """Z-Y-X Euler angles ``(roll, pitch, yaw)`` [rad] (see :func:`euler_from_quaternion`)."""
        return _euler(*self._x[6:10])

    @property
    def motor_thrusts(self) -> np.ndarray:
        """Motor thrusts now (4,) [N], M1..M4."""
        return np.array(self._f)

    @property
    def motor_commands(self) -> np.ndarray:
        """Motor thrust commands of the last control tick (4,) [N], within ``[0, f_max]``."""
        return np.array(self._fc)

    @property
    def rotor_speeds(self) -> np.ndarray:
        """Rotor speeds (4,) [rad/s], ``sqrt(f / k_f)``."""
        return np.sqrt(np.array(self._f) / self.params.thrust_coeff)

    @property
    def attitude_setpoint(self) -> tuple[float, float, float, float]:
        """``(T [N], roll [rad], pitch [rad], yaw [rad])`` the inner loop tracked at the last tick."""
        return self._setpoint

    @property
    def z_integrator(self) -> float:
        """The vertical integrator's correction of ``u_z`` [m/s^2] (0 when it is off)."""
        return self.params.z_integrator_gain * self._zi

    def accel(self) -> np.ndarray:
        """Mean acceleration of the centre of mass over the last :meth:`advance` span (3,) [m/s^2;
        world frame], i.e. ``(v_end - v_start) / dt`` = the mean of ``p''`` (gravity excluded, as an
        accelerometer averaged over the span and rotated to the world would read after removing
        gravity). Zero before the first advance."""
        return np.array(self._accel)

    # ------------------------------------------------------------------------------- commands
    def command(self, u: np.ndarray, yaw: float = 0.0) -> None:
        """Desired acceleration ``u`` (3,) [m/s^2; world frame, z up] and yaw [rad], through Eq. 4 at
        every control tick; held until the next command. Returns immediately."""
        ux, uy, uz = (float(c) for c in np.broadcast_to(np.asarray(u, dtype=float), (3,)))
        if not all(math.isfinite(c) for c in (ux, uy, uz, yaw)):
            raise ValueError(f"command: u = {u!r}, yaw = {yaw!r}; use finite numbers")
        self._switch("accel")
        self._u = (ux, uy, uz)
        self._yaw_cmd = float(yaw)

    def command_attitude(self, thrust: float, roll: float, pitch: float, yaw_rate: float) -> None:
        """A Crazyflie commander setpoint: collective thrust [N], roll and pitch [rad; Eq. 2's Z-Y-X
        angles] and yaw rate [rad/s, integrated into the yaw setpoint]; held until the next command.
        ``thrust = 0`` switches the motors off. Returns immediately."""
        vals = (float(thrust), float(roll), float(pitch), float(yaw_rate))
        if not all(math.isfinite(c) for c in vals) or vals[0] < 0:
            raise ValueError(f"command_attitude: {vals}; use finite numbers and thrust >= 0")
        if self._switch("attitude"):
            self._yaw_d = self.euler()[2]
        self._thrust_cmd, self._roll_cmd, self._pitch_cmd, self._yaw_rate_cmd = vals

    def _switch(self, mode: Mode) -> bool:
        """Enter ``mode``; a change resets the PIDs (as the firmware does on a setpoint-mode change)."""
        if mode == self._mode:
            return False
        self._mode = mode
        self._reset_pids()
        self._zi, self._vz_tick = 0.0, None
        self._ii, self._v_tick = (0.0, 0.0, 0.0), None
        return True

    # -------------------------------------------------------------------------------- stepping
    def advance(self, dt: float, f_ext: np.ndarray | None = None) -> None:
        """Integrate ``dt`` seconds (any ``dt > 0``; rounded to whole nanoseconds) with the external
        force ``f_ext`` (3,) [N; world frame] held. The inner loop runs on its own schedule (every
        ``1 / control_rate`` s since construction), the physics in fixed RK4 steps between its ticks."""
        n_ns = round(dt * 1e9) if math.isfinite(dt) else 0
        if not n_ns > 0:
            raise ValueError(f"advance: dt = {dt!r}; use a finite dt > 0 (at least 1 ns)")
        if f_ext is None:
            fx = fy = fz = 0.0
        else:
            fx, fy, fz = (float(c) for c in np.broadcast_to(np.asarray(f_ext, dtype=float), (3,)))
            if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
                raise ValueError(f"advance: f_ext = {f_ext!r}; use finite numbers")
        x = self._x
        v0 = (x[3], x[4], x[5])
        t_end = self._t_ns + n_ns
        hp = self._hp_ns
        while self._t_ns < t_end:
            if self._t_ns >= self._next_ctrl_ns:
                self._control()
                self._next_ctrl_ns += self._hc_ns
            t_next = min(t_end, (self._t_ns // hp + 1) * hp)
            self._rk4(t_next - self._t_ns, fx, fy, fz)
            self._t_ns = t_next
        x = self._x
        span = n_ns * 1e-9
        self._accel = ((x[3] - v0[0]) / span, (x[4] - v0[1]) / span, (x[5] - v0[2]) / span)

    def _rk4(self, h_ns: int, fx: float, fy: float, fz: float) -> None:
        """One classical RK4 step of ``h_ns`` nanoseconds of Eq. 1, the quaternion renormalised after it.

        The motor thrusts, hence the wrench, are known in closed form at every stage (constant with
        ideal motors; ``W_c + (W_0 - W_c) exp(-s / tau_m)`` with a lag). As ``p`` and ``v`` do not enter
        the right-hand side, their RK4 stages reduce to ``v+ = v + h/6 (a1 + 2 a2 + 2 a3 + a4)`` and
        ``p+ = p + h v + h^2/6 (a1 + a2 + a3)``: the same numbers as RK4 on all 13 states.
        """
        h = h_ns * 1e-9
        c1, c2, c3, c4 = self._fc
        a, c = self._a, self._c
        t4 = c1 + c2 + c3 + c4
        x4, y4, z4 = a * (-c1 - c2 + c3 + c4), a * (-c1 + c2 + c3 - c4), c * (-c1 + c2 - c3 + c4)
        t1, x1, y1, z1 = t2, x2, y2, z2 = t4, x4, y4, z4
        tau_m = self._tau_m
        if tau_m > 0.0:
            dec = self._decay.get(h_ns)
            if dec is None:
                dec = self._decay[h_ns] = (math.exp(-0.5 * h / tau_m), math.exp(-h / tau_m))
            e2, e4 = dec
            g1, g2, g3, g4 = self._f
            dt_ = g1 + g2 + g3 + g4 - t4
            dx = a * (-g1 - g2 + g3 + g4) - x4
            dy = a * (-g1 + g2 + g3 - g4) - y4
            dz = c * (-g1 + g2 - g3 + g4) - z4
            t1, x1, y1, z1 = t4 + dt_, x4 + dx, y4 + dy, z4 + dz
            t2, x2, y2, z2 = t4 + dt_ * e2, x4 + dx * e2, y4 + dy * e2, z4 + dz * e2
            t4, x4, y4, z4 = t4 + dt_ * e4, x4 + dx * e4, y4 + dy * e4, z4 + dz * e4
            self._f = [q + (r - q) * e4 for q, r in zip(self._fc, self._f)]
        else:
            self._f = list(self._fc)
        px, py, pz, vx, vy, vz, qw, qx, qy, qz, wx, wy, wz = self._x
        f = self._rhs
        hh = 0.5 * h
        k1 = f(qw, qx, qy, qz, wx, wy, wz, t1, x1, y1, z1)
        k2 = f(qw + hh * k1[3], qx + hh * k1[4], qy + hh * k1[5], qz + hh * k1[6],
               wx + hh * k1[7], wy + hh * k1[8], wz + hh * k1[9], t2, x2, y2, z2)
        k3 = f(qw + hh * k2[3], qx + hh * k2[4], qy + hh * k2[5], qz + hh * k2[6],
               wx + hh * k2[7], wy + hh * k2[8], wz + hh * k2[9], t2, x2, y2, z2)
        k4 = f(qw + h * k3[3], qx + h * k3[4], qy + h * k3[5], qz + h * k3[6],
               wx + h * k3[7], wy + h * k3[8], wz + h * k3[9], t4, x4, y4, z4)
        h6 = h / 6.0
        hh6 = h * h6
        inv_m = 1.0 / self.mass
        ex, ey, ez = fx * inv_m, fy * inv_m, fz * inv_m - self._g
        hh2 = 0.5 * h * h
        qw += h6 * (k1[3] + 2.0 * (k2[3] + k3[3]) + k4[3])
        qx += h6 * (k1[4] + 2.0 * (k2[4] + k3[4]) + k4[4])
        qy += h6 * (k1[5] + 2.0 * (k2[5] + k3[5]) + k4[5])
        qz += h6 * (k1[6] + 2.0 * (k2[6] + k3[6]) + k4[6])
        n = 1.0 / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        self._x = [
            px + h * vx + hh2 * ex + hh6 * (k1[0] + k2[0] + k3[0]),
            py + h * vy + hh2 * ey + hh6 * (k1[1] + k2[1] + k3[1]),
            pz + h * vz + hh2 * ez + hh6 * (k1[2] + k2[2] + k3[2]),
            vx + h * ex + h6 * (k1[0] + 2.0 * (k2[0] + k3[0]) + k4[0]),
            vy + h * ey + h6 * (k1[1] + 2.0 * (k2[1] + k3[1]) + k4[1]),
            vz + h * ez + h6 * (k1[2] + 2.0 * (k2[2] + k3[2]) + k4[2]),
            qw * n, qx * n, qy * n, qz * n,
            wx + h6 * (k1[7] + 2.0 * (k2[7] + k3[7]) + k4[7]),
            wy + h6 * (k1[8] + 2.0 * (k2[8] + k3[8]) + k4[8]),
            wz + h6 * (k1[9] + 2.0 * (k2[9] + k3[9]) + k4[9]),
        ]

    # ------------------------------------------------------------------------------ inner loop
    def _reset_pids(self) -> None:
        self._att_i = (0.0, 0.0, 0.0)
        self._rate_i = (0.0, 0.0, 0.0)
        self._att_prev: tuple[float, float, float] | None = None
        self._rate_prev: tuple[float, float, float] | None = None

    def _integrate_xyz(self, u: tuple[float, float, float], v: tuple[float, float, float],
                       h: float) -> tuple[float, float, float]:
        """``integrator_axes = "xyz"``: the vertical integrator's rule on every axis."""
        p = self.params
        lim = p.z_integrator_limit / p.z_integrator_gain
        if self._v_tick is not None:
            ix, iy, iz = (min(max(i + (ut - (vn - vt) / h) * h, -lim), lim)
                          for i, ut, vn, vt in zip(self._ii, self._u_tick, v, self._v_tick))
            self._ii = (ix, iy, iz)
        self._v_tick, self._u_tick = v, u
        k = p.z_integrator_gain
        return u[0] + k * self._ii[0], u[1] + k * self._ii[1], u[2] + k * self._ii[2]

    def _control(self) -> None:
        """One inner-loop tick: setpoint -> attitude PID -> Eq. 3 -> rate PID -> mixer."""
        p = self.params
        h = self._hc
        x = self._x
        roll, pitch, yaw = _euler(x[6], x[7], x[8], x[9])
        wx, wy, wz = x[10], x[11], x[12]
        sat_eq4 = False
        if self._mode == "accel":
            ux, uy, uz = self._u
            if p.z_integrator_gain > 0.0:
                if p.integrator_axes == "z":
                    if self._vz_tick is not None:
                        # the mean vertical acceleration over the last period against what was asked for it
                        lim = p.z_integrator_limit / p.z_integrator_gain
                        zi = self._zi + (self._uz_tick - (x[5] - self._vz_tick) / h) * h
                        self._zi = lim if zi > lim else -lim if zi < -lim else zi
                    self._vz_tick, self._uz_tick = x[5], uz
                    uz = uz + p.z_integrator_gain * self._zi
                else:
                    ux, uy, uz = self._integrate_xyz((ux, uy, uz), (x[3], x[4], x[5]), h)
            thrust, roll_d, pitch_d, sat_eq4 = eq4((ux, uy, uz), self._yaw_cmd, self._eq4_mass,
                                                   self._g, p.tilt_max, self._thrust_max)
            yaw_d = self._yaw_cmd
        else:
            thrust, roll_d, pitch_d = self._thrust_cmd, self._roll_cmd, self._pitch_cmd
            self._yaw_d = wrap_angle(self._yaw_d + self._yaw_rate_cmd * h)
            yaw_d = self._yaw_d
        self._setpoint = (thrust, roll_d, pitch_d, yaw_d)
        sat = self.saturation
        sat.ticks += 1
        sat.eq4 += sat_eq4
        if thrust <= 0.0:
            # the firmware's rule: zero thrust = motors off, PIDs reset
            self._fc = [0.0, 0.0, 0.0, 0.0]
            self._reset_pids()
            if self._mode == "attitude":
                self._yaw_d = yaw
            self.saturated = sat_eq4
            return

        # attitude PID on the Euler angles (derivative on the measurement, integral clamped)
        kp, ki, kd, il = p.att_kp, p.att_ki, p.att_kd, p.att_ilimit
        prev = self._att_prev
        if prev is None:
            prev = (roll, pitch, yaw)
        e0, e1, e2 = roll_d - roll, pitch_d - pitch, wrap_angle(yaw_d - yaw)
        i0, i1, i2 = self._att_i
        i0 = min(max(i0 + e0 * h, -il[0]), il[0])
        i1 = min(max(i1 + e1 * h, -il[1]), il[1])
        i2 = min(max(i2 + e2 * h, -il[2]), il[2])
        self._att_i = (i0, i1, i2)
        self._att_prev = (roll, pitch, yaw)
        dr = kp[0] * e0 + ki[0] * i0 - kd[0] * (roll - prev[0]) / h
        dp = kp[1] * e1 + ki[1] * i1 - kd[1] * (pitch - prev[1]) / h
        dy = kp[2] * e2 + ki[2] * i2 - kd[2] * wrap_angle(yaw - prev[2]) / h
        # Euler-rate setpoint -> body-rate setpoint (Eq. 3)
        sr, cr, sp, cp = math.sin(roll), math.cos(roll), math.sin(pitch), math.cos(pitch)
        s0, s1, s2 = dr - sp * dy, cr * dp + sr * cp * dy, -sr * dp + cr * cp * dy

        # body-rate PID (derivative on the measurement, integral clamped) -> torque [N m]
        kp, ki, kd, il = p.rate_kp, p.rate_ki, p.rate_kd, p.rate_ilimit
        prev = self._rate_prev
        if prev is None:
            prev = (wx, wy, wz)
        e0, e1, e2 = s0 - wx, s1 - wy, s2 - wz
        i0, i1, i2 = self._rate_i
        i0 = min(max(i0 + e0 * h, -il[0]), il[0])
        i1 = min(max(i1 + e1 * h, -il[1]), il[1])
        i2 = min(max(i2 + e2 * h, -il[2]), il[2])
        self._rate_i = (i0, i1, i2)
        self._rate_prev = (wx, wy, wz)
        tm = p.torque_max
        tx = min(max(kp[0] * e0 + ki[0] * i0 - kd[0] * (wx - prev[0]) / h, -tm[0]), tm[0])
        ty = min(max(kp[1] * e1 + ki[1] * i1 - kd[1] * (wy - prev[1]) / h, -tm[1]), tm[1])
        tz = min(max(kp[2] * e2 + ki[2] * i2 - kd[2] * (wz - prev[2]) / h, -tm[2]), tm[2])

        f1, f2, f3, f4, sat_m = _mix(thrust, tx, ty, tz, self._ka, self._kc, p.motor_thrust_max)
        self._fc = [f1, f2, f3, f4]
        self.saturated = sat_eq4 or sat_m
        sat.motors += sat_m
