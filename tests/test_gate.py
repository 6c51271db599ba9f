"""The plausibility gate's rules beyond single-sample physics (pure, no I/O).

* ``profile``: the leader's samples are checked against the mission's profile at their own time
  (:func:`leader.profile.scalar`, tested equal to the arrays the leader publishes);
* :class:`tether.gate.Health`: a stream mostly rejected over its window is suspect, with hysteresis;
* :class:`tether.inputs.Source`: two samples of one tick with different contents are a conflict;
* :class:`tether.gate.PlantModes`: a plant's mode report is believed only as far as its samples agree.
"""

from __future__ import annotations

import msgspec

import math

import pytest

from leader import profile
from tether import wire
from tether.catalog import builtin_path
from tether.gate import Health, PlantModes, for_sender
from tether.inputs import Source
from tether.node import load_mission
from tether.wire import ESTOP, FLYING, HOLD, LAND

SHIPPED = ["exp1", "exp1_cf", "exp2", "failsafe", "section4", "swap"]


def leader_sample(m, k: int, dp: float = 0.0, seq: int | None = None) -> wire.State:
    p, v, a = profile.scalar(m.leader, m.dim)(k * m.dt)
    return wire.State(sender=m.leader.id, seq=k if seq is None else seq, k=k, t=k * m.dt, p=[p[0] + dp, *p[1:]],
                      vel=v, a=a)


@pytest.mark.parametrize("name", SHIPPED)
def test_the_scalar_profile_is_what_the_leader_publishes(name: str) -> None:
    """Every tick of every shipped mission: the agent's float evaluation and the leader's arrays
    (``at_ticks``) differ by rounding at most (0 measured)."""
    m = load_mission(builtin_path(name))
    at = profile.scalar(m.leader, m.dim)
    p, v, a = profile.at_ticks(profile.build(m.leader, m.dim), m.dt, 0, m.steps + 1, m.dim)
    worst = 0.0
    for k in range(0, m.steps + 1, max(1, m.steps // 3000)):
        ps, vs, as_ = at(k * m.dt)
        worst = max(worst, max(abs(x - y) for x, y in zip(ps + vs + as_, p[k] + v[k] + a[k])))
    assert worst <= 1e-9


@pytest.mark.parametrize("name", SHIPPED)
def test_the_leaders_genuine_samples_pass_and_a_drift_is_rejected_once_past_the_margin(name: str) -> None:
    m = load_mission(builtin_path(name))
    g = for_sender(m, m.leader.id, None, expect=profile.scalar(m.leader, m.dim))
    assert all(g.check(leader_sample(m, k)) is None for k in range(m.steps + 1))
    # a drift of 0.5 m/s from t = 1 s: plausible for the jump rule, rejected by the profile within 2 cm
    g = for_sender(m, m.leader.id, None, expect=profile.scalar(m.leader, m.dim))
    start = int(1.0 / m.dt)
    verdicts = [g.check(leader_sample(m, k, dp=0.5 * max(0, k - start) * m.dt)) for k in range(start + 200)]
    first = verdicts.index("profile")
    assert all(v is None for v in verdicts[:first]) and set(verdicts[first:]) == {"profile"}
    assert 0.5 * (first - start) * m.dt <= m.safety.profile_margin + 0.5 * m.dt
    assert g.rejected == {"profile": len(verdicts) - first}


def test_a_velocity_or_acceleration_off_the_profile_is_rejected_too() -> None:
    m = load_mission(builtin_path("section4"))
    g = for_sender(m, m.leader.id, None, expect=profile.scalar(m.leader, m.dim))
    good = leader_sample(m, 10)
    fast = wire.State(sender=5, seq=10, k=10, t=good.t, p=good.p, vel=[good.vel[0] + 0.1, good.vel[1]], a=good.a)
    push = wire.State(sender=5, seq=10, k=10, t=good.t, p=good.p, vel=good.vel, a=[good.a[0], 0.5])
    assert g.check(fast) == "profile" and g.check(push) == "profile" and g.check(good) is None


def test_health_turns_suspect_at_the_share_and_clears_only_at_half_of_it() -> None:
    h = Health(window=10, share=0.5)
    assert not any(h.note(True) for _ in range(4))  # a first few rejections: never enough alone
    assert h.note(True) and h.suspect  # 5 of a full window of 10
    for _ in range(3):
        h.note(False)
    assert h.suspect  # alternating around the threshold does not flap
    changed = [h.note(False) for _ in range(10)]
    assert not h.suspect and changed.count(True) == 1
    h.note(True)
    h.reset()
    assert (h.bad, h.suspect, len(h.outcomes)) == (0, False, 0)


def test_half_the_samples_rejected_for_ever_is_suspect_for_ever() -> None:
    """A forger as fast as the genuine sender, one of two samples rejected: suspect, and it stays."""
    h = Health(window=50, share=0.5)
    flips = [h.note(i % 2 == 0) for i in range(1000)]
    assert h.suspect and flips.count(True) == 1


def state(k: int, x: float, mode: int = FLYING, seq: int | None = None) -> wire.State:
    return wire.State(sender=1, seq=k if seq is None else seq, k=k, t=k * 0.01, p=[x, 0.0], vel=[0.0, 0.0],
                      a=[0.0, 0.0], mode=mode)


def test_two_samples_of_one_tick_that_disagree_are_a_conflict_and_the_second_is_dropped() -> None:
    src = Source("agent/1/state", wire.State, 1, health=Health(window=4, share=0.5))
    first = state(3, 1.0)
    src.offer(first)
    src.offer(state(3, 1.0))  # the same sample again (a copy, a resend): no conflict
    src.offer(state(3, 1.2, seq=4))  # another truth for tick 3
    src.offer(state(3, 1.0, mode=HOLD, seq=5))  # another mode for tick 3
    assert src.conflicts == 2 and src.by_tick[3] is first and src.newest.seq == 3
    # the tick is contested: the held sample's verdict is bad too (three bad: held, and both others)
    assert src.health is not None and src.health.suspect and src.health.bad == 3
    assert src.is_contested(first) and src.contested == {3: 2}
    src.forget_before(4)
    assert src.contested == {}


def test_a_one_for_one_forgery_makes_two_thirds_of_the_window_bad() -> None:
    """One forged copy beside each genuine sample: every tick is contested, so two of every three
    verdicts are bad, well past the share of a half (before, the forger sat right at it)."""
    src = Source("agent/1/state", wire.State, 1, health=Health(window=50, share=0.5))
    became = None
    for k in range(60):
        genuine = state(k, 0.01 * k, seq=2 * k)
        src.offer(genuine)
        src.offer(msgspec.structs.replace(genuine, seq=2 * k + 1, mode=HOLD))
        if became is None and src.health is not None and src.health.suspect:
            became = k
    assert src.health is not None and src.health.suspect and src.health.bad in (33, 34)
    assert became is not None and became <= 12  # 25 bad verdicts: the 13th tick's pair


def test_a_genuine_stream_alone_contests_nothing() -> None:
    src = Source("agent/1/state", wire.State, 1, health=Health(window=50, share=0.5))
    for k in range(200):
        msg = state(k, 0.01 * k, seq=k)
        src.offer(msg)
        src.offer(msg)  # a network's duplicate
    assert src.conflicts == 0 and src.contested == {} and src.health is not None and src.health.bad == 0


def test_two_commands_of_one_tick_with_other_u_are_a_conflict() -> None:
    """A command's contents are its ``u`` and mode: a copy of the genuine command with another
    ``u`` under the same number is a conflict, the tick contested."""
    src = Source("agent/2/cmd", wire.Command, 2, health=Health(window=50, share=0.5))
    genuine = wire.Command(sender=2, seq=7, k=7, t=0.07, u=[0.1, 0.2])
    src.offer(genuine)
    src.offer(msgspec.structs.replace(genuine, u=[20.0, 0.0]))
    assert src.conflicts == 1 and src.by_tick[7] is genuine and src.is_contested(genuine)
    src.offer(wire.Command(sender=2, seq=8, k=8, t=0.08, u=[0.1, 0.2]))
    assert src.contested == {7: 1}


def test_a_second_sample_of_a_held_tick_under_another_number_is_a_conflict_even_if_equal() -> None:
    """A forger copying each genuine sample as it is (only its sequence number moved on, as a
    publisher's would) says nothing false, but it is someone else on the key: a conflict, dropped.
    A copy under the same number (a network's duplicate, a lockstep resend) is none."""
    src = Source("agent/1/state", wire.State, 1, health=Health(window=50, share=0.5))
    for k in range(100):
        genuine = state(k, 0.01 * k, seq=k)
        src.offer(genuine)
        src.offer(msgspec.structs.replace(genuine, seq=k + 1))  # the forger's copy
        src.offer(genuine)  # a duplicate on the way
        assert src.by_tick[k] is genuine
    assert src.conflicts == 100 and src.duplicates == 100 and src.health is not None and src.health.suspect


def test_without_a_health_judge_a_source_keeps_its_old_behaviour() -> None:
    src = Source("k", wire.State, 1)
    src.offer(state(3, 1.0))
    src.offer(state(3, 2.0, seq=4))
    assert src.conflicts == 0 and src.newest.seq == 4


def test_a_plant_mode_is_believed_after_confirm_consecutive_ticks() -> None:
    pm = PlantModes(confirm=3)
    assert all(pm.observe(k, FLYING) for k in range(5))
    assert pm.observe(5, LAND) and pm.believed == FLYING
    assert pm.observe(6, LAND) and pm.believed == FLYING
    assert pm.observe(7, LAND) and pm.believed == LAND
    assert not pm.observe(8, FLYING) and pm.believed == LAND  # never flies again on a report
    assert pm.contradictions == 1


def test_one_forged_estop_between_genuine_flying_samples_is_never_believed() -> None:
    pm = PlantModes(confirm=3)
    verdicts = []
    for k in range(20):
        verdicts.append(pm.observe(k, FLYING))
        if k == 7:
            verdicts.append(pm.observe(k + 1, ESTOP))  # forged, for the next tick, before the genuine one
        assert pm.believed == FLYING
    assert verdicts.count(False) == 1 and pm.contradictions == 1


def test_a_plant_hold_that_ends_is_no_contradiction() -> None:
    pm = PlantModes(confirm=2)
    for k, mode in enumerate([FLYING, HOLD, HOLD, HOLD, FLYING, FLYING]):
        assert pm.observe(k, mode)
        if k == 2:
            assert pm.believed == HOLD
    assert pm.believed == FLYING and pm.contradictions == 0


def test_the_profile_margin_and_windows_are_checked_with_the_field_named() -> None:
    from tether import mission as ms

    text = open(builtin_path("section4")).read()
    for field, bad in (("profile_margin", "0.0"), ("suspect_window", "1"), ("suspect_share", "1.5"),
                       ("mode_confirm", "0")):
        with pytest.raises(ms.MissionError, match=f"safety.{field}"):
            ms.loads(text.replace("[law]", f"[safety]\n{field} = {bad}\n\n[law]", 1))
    assert math.isclose(load_mission(builtin_path("section4")).safety.profile_margin, 0.01)
