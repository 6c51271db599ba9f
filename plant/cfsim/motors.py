"""The simulated Crazyflie's thrust map (crazyflie-firmware ``motors.c`` with battery compensation,
the default). Pure.

A motor command ``pwm`` in 0..65535 gives ``pwm / 65535 * f_max`` newtons per motor, ``f_max`` being
:attr:`plant.quadrotor.QuadrotorParams.motor_thrust_max` (THRUST_MAX, 0.1125 N for the CF 2.1
propellers). An RPYT thrust therefore means a collective thrust ``T = 4 f_max pwm / 65535``.
"""

from __future__ import annotations

PWM_FULL = 65535
"""Full-scale motor command [PWM units]."""


def pwm_to_thrust(pwm: float, motor_thrust_max: float) -> float:
    """Collective thrust [N] of four motors commanded at ``pwm`` [0..65535]."""
    return 4.0 * motor_thrust_max * pwm / PWM_FULL


def thrust_to_pwm(thrust: float, motor_thrust_max: float) -> float:
    """The PWM command [0..65535, not clipped] that gives collective thrust ``thrust`` [N]."""
    return thrust * PWM_FULL / (4.0 * motor_thrust_max)
