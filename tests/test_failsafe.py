"""tether/failsafe.py's anchor: HOLD from :func:`hold_point` stops there without turning back."""

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from tether import failsafe
from tether.vec import dot


def _fly_hold(p: list[float], v: list[float], anchor: list[float], kp: float, kv: float, max_accel: float,
              h: float = 0.001, seconds: float = 12.0) -> tuple[list[float], float]:
    """HOLD's law flown on a double integrator (semi-implicit Euler); the end point and the least
    velocity component along the initial direction of motion (negative: it turned back)."""
    d = [c / math.sqrt(dot(v, v)) for c in v]
    least = math.inf
    for _ in range(int(seconds / h)):
        u = failsafe.hold(p, v, anchor, kp, kv, max_accel)
        v = [vc + uc * h for vc, uc in zip(v, u)]
        p = [pc + vc * h for pc, vc in zip(p, v)]
        least = min(least, dot(v, d))
    return p, least


@settings(max_examples=40, deadline=None)
@given(speed=st.floats(0.1, 35.0), angle=st.floats(0.0, 2 * math.pi))
def test_a_vehicle_held_from_speed_comes_to_rest_at_its_anchor_without_turning_back(speed: float,
                                                                                    angle: float) -> None:
    kp, kv, max_accel = 1.0, 2.0, 20.0  # the [safety] defaults: critically damped
    p0, v0 = [3.0, -2.0], [speed * math.cos(angle), speed * math.sin(angle)]
    anchor = failsafe.hold_point(p0, v0, kp, max_accel)
    end, least = _fly_hold(p0, v0, anchor, kp, kv, max_accel)
    assert math.dist(end, anchor) < 0.01 * (1.0 + speed)
    assert least > -0.02 * speed  # no reversal beyond the integration's error


def test_the_anchor_where_hold_begins_turns_a_fast_vehicle_back_a_long_way() -> None:
    """Why the anchor is ahead: held about where HOLD began, a vehicle at 10 m/s runs on 3.7 m
    (``10 t e^-t`` at its peak) and flies back through the formation behind it at up to 1.35 m/s."""
    kp, kv, max_accel = 1.0, 2.0, 20.0
    _, least = _fly_hold([0.0, 0.0], [10.0, 0.0], [0.0, 0.0], kp, kv, max_accel)
    assert least < -1.3


def test_the_anchor_is_the_position_at_rest_or_with_a_velocity_that_is_not_finite() -> None:
    assert failsafe.hold_point([1.0, 2.0], [0.0, 0.0], 1.0, 20.0) == [1.0, 2.0]
    assert failsafe.hold_point([1.0, 2.0], [math.nan, 0.0], 1.0, 20.0) == [1.0, 2.0]
    assert failsafe.hold_point([1.0, 2.0], [math.inf, 0.0], 1.0, 20.0) == [1.0, 2.0]


def test_a_3d_anchor_is_never_below_the_floor() -> None:
    assert failsafe.hold_point([0.0, 0.0, 1.0], [0.0, 0.0, -3.0], 1.0, 20.0, floor=0.0)[-1] == 0.0
    assert failsafe.hold_point([0.0, 0.0, 1.0], [0.0, 0.0, 3.0], 1.0, 20.0, floor=0.0)[-1] == 4.0


def test_the_stopping_distance_is_continuous_at_the_saturation_knee() -> None:
    knee = 20.0 / math.sqrt(1.0)
    below = failsafe.stopping_distance(knee * (1 - 1e-12), 1.0, 20.0)
    above = failsafe.stopping_distance(knee * (1 + 1e-12), 1.0, 20.0)
    assert abs(above - below) < 1e-9
