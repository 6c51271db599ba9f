"""The simulated Crazyflie's controller: a setpoint and the state estimate in, a command of the
quadrotor out. Pure.

Attitude setpoints become ``command_attitude(T, roll, pitch, yaw_rate)``; position setpoints become
``command(u, yaw)`` with ``u = a_ref + Kp (p_ref - p) + Kv (v_ref - v)`` (Eq. 4 inside
:class:`plant.quadrotor.Quadrotor`); velocity and hover setpoints a velocity loop, the z-distance
setpoint a height loop under the given tilt. An axis whose reference is NaN (the supervisor's
level-out) gets no command.
"""

from __future__ import annotations

import math

import numpy as np

from plant.cfsim.commander import Attitude, Hover, Manual, Off, Setpoint, Track, ZHold
from plant.cfsim.motors import pwm_to_thrust
from plant.quadrotor import Quadrotor, wrap_angle


class Controller:
    """The controller of one vehicle, run once a control period. Not thread-safe; calls return at
    once.

    ``kp`` [1/s^2] and ``kv`` [1/s] are the position loop's gains, ``kv_velocity`` [1/s] the velocity
    loop's (x, y, z); ``tilt_max_manual`` [rad] bounds the roll and pitch integrated from manual rate
    setpoints; ``period`` [s] is the control period.
    """

    def __init__(self, quad: Quadrotor, kp: tuple[float, float, float], kv: tuple[float, float, float],
                 kv_velocity: tuple[float, float, float], tilt_max_manual: float, period: float) -> None:
        self.quad = quad
        self.kp, self.kv, self.kv_velocity = kp, kv, kv_velocity
        self.tilt_max_manual = tilt_max_manual
        self.period = period
        self._fmax = quad.params.motor_thrust_max
        self._g = quad.params.g
        self._vel_yaw: float | None = None
        """Yaw [rad] integrated from the yaw rate of velocity and hover setpoints; None otherwise."""
        self._manual_att = (0.0, 0.0)
        """Roll and pitch [rad] integrated from manual rate setpoints."""

    def command(self, sp: Setpoint, p: np.ndarray, v: np.ndarray) -> None:
        """Command the quadrotor towards ``sp`` from the estimated position ``p`` [m; world] and
        velocity ``v`` [m/s; world]."""
        quad = self.quad
        if isinstance(sp, Off):
            quad.command_attitude(0.0, 0.0, 0.0, 0.0)
            self._vel_yaw = None
        elif isinstance(sp, Attitude):
            quad.command_attitude(pwm_to_thrust(sp.thrust_pwm, self._fmax), sp.roll, sp.pitch, sp.yaw_rate)
            self._vel_yaw = None
        elif isinstance(sp, Manual):
            self._manual(sp)
        elif isinstance(sp, ZHold):
            uz = self.kp[2] * (sp.z - p[2]) - self.kv[2] * v[2]
            tilt = max(0.1, math.cos(sp.roll) * math.cos(sp.pitch))
            thrust = min(quad.params.collective_thrust_max, max(0.0, quad.mass * (self._g + uz) / tilt))
            quad.command_attitude(thrust, sp.roll, sp.pitch, sp.yaw_rate)
            self._vel_yaw = None
        elif isinstance(sp, Hover):
            yaw = self._turn(sp.yaw_rate)
            c, s = math.cos(yaw), math.sin(yaw)
            vref = (c * sp.vx_body - s * sp.vy_body, s * sp.vx_body + c * sp.vy_body)
            kv = self.kv_velocity
            u = [kv[0] * (vref[0] - v[0]), kv[1] * (vref[1] - v[1]),
                 self.kp[2] * (sp.z - p[2]) - self.kv[2] * v[2]]
            quad.command(np.array(u), yaw)
        elif isinstance(sp, Track):
            kp, kv = self.kp, self.kv
            u = [0.0 if math.isnan(sp.pos[i]) else
                 sp.acc[i] + kp[i] * (sp.pos[i] - p[i]) + kv[i] * (sp.vel[i] - v[i]) for i in range(3)]
            quad.command(np.array(u), sp.yaw)
            self._vel_yaw = None
        else:
            kv = self.kv_velocity
            yaw = self._turn(sp.yaw_rate)
            u = [0.0 if math.isnan(sp.vel[i]) else kv[i] * (sp.vel[i] - v[i]) for i in range(3)]
            quad.command(np.array(u), yaw)

    def _manual(self, sp: Manual) -> None:
        if sp.rate:
            lim = self.tilt_max_manual
            r, pt = self._manual_att
            self._manual_att = (max(-lim, min(lim, r + sp.roll * self.period)),
                                max(-lim, min(lim, pt + sp.pitch * self.period)))
        else:
            self._manual_att = (sp.roll, sp.pitch)
        self.quad.command_attitude(pwm_to_thrust(sp.thrust_pwm, self._fmax), *self._manual_att, sp.yaw_rate)
        self._vel_yaw = None

    def _turn(self, yaw_rate: float) -> float:
        """Integrate ``yaw_rate`` [rad/s] over one period from the present yaw (or the vehicle's, when
        a velocity or hover setpoint begins); returns the new yaw [rad]."""
        if self._vel_yaw is None:
            self._vel_yaw = self.quad.euler()[2]
        self._vel_yaw = wrap_angle(self._vel_yaw + yaw_rate * self.period)
        return self._vel_yaw
