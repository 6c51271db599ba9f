"""The supervisor's rule between FLYING, HOLD and LAND (:func:`agent.safety.transition` and its
helpers): no flapping, and one definition that the in-process engine's compiled twin runs."""

from __future__ import annotations

import ast
import inspect
import math
import textwrap
from collections.abc import Callable, Iterator
from typing import Any

import msgspec
import numpy as np
import pytest

from agent import safety
from agent.safety import Supervisor
from sim import lockstep, lockstep_kernel
from tether import failsafe, wire
from tether.catalog import builtin_path
from tether.netprofile import Bernoulli, LinkProfile, LinkRule, Network
from tether.node import load_mission
from tether.wire import FLYING, HOLD, LAND
from tests.test_lockstep_kernel import compiled_equals_python
from tests.test_safety import mission, step

replace = msgspec.structs.replace
H = 0.01


def run_rule(pattern: Callable[[float], bool], seconds: float, *, land_after: float = 2.0, flap_limit: int = 3,
             resume_dwell: float = 0.5) -> Iterator[tuple[float, int, int]]:
    """:func:`agent.safety.transition` ticked at 100 Hz while ``pattern(t)`` says whether the leader
    is silent; yields ``(t, mode, kind)`` for every tick that is not :data:`~agent.safety.STAY`,
    and stops when the vehicle lands."""
    mode, cause, latched, since, healthy, flaps, last = FLYING, 0, False, 0.0, math.nan, 0, -math.inf
    for k in range(int(round(seconds / H)) + 1):
        t = k * H
        why = safety.LEADER if pattern(t) else 0
        mode, cause, latched, since, healthy, flaps, last, kind = safety.transition(
            mode, cause, latched, since, healthy, flaps, last, why, t, land_after, flap_limit, resume_dwell)
        if kind != safety.STAY:
            yield t, mode, kind
        if mode == LAND:
            return


def skewed(t: float) -> bool:
    """The measured flapping: the input lost for just under ``land_after`` (1.9 s), back for 0.6 s."""
    return t % 2.5 < 1.9


def most_recoveries_in_a_window(times: list[float]) -> int:
    """The most recoveries within any :data:`agent.safety.FLAP_WINDOW`."""
    return max((sum(1 for b in times if a <= b < a + safety.FLAP_WINDOW) for a in times), default=0)


# ------------------------------------------------------------------------------ the rule, pure
def test_an_input_lost_just_under_land_after_again_and_again_escalates_to_land() -> None:
    """The escalation alone (no dwell): exactly ``flap_limit`` recoveries, then the next loss is a
    LAND at once, which says why."""
    out = list(run_rule(skewed, 120.0, resume_dwell=0.0))
    recoveries = [t for t, _, kind in out if kind == safety.RECOVERED]
    assert len(recoveries) == 3
    t_end, mode, kind = out[-1]
    assert (mode, kind) == (LAND, safety.LAND_FLAPPING)
    assert t_end < 4 * 2.5  # the fourth loss, at its first tick past the cause
    assert safety.reason(kind, "leader", 3, 2.0, 0.0).startswith("flapping: leader again after 3 recoveries")


def test_a_resume_waits_longer_after_each_recent_recovery_and_a_hold_that_waits_too_long_lands() -> None:
    """The dwell alone (``flap_limit`` out of reach): the input lost for 1 s in every 2.5 s. The
    first recovery is at once, each next one waits ``resume_dwell`` (0.3 s) more after the cause is
    gone; the one whose wait would run past ``land_after`` lands, the event saying so."""
    out = list(run_rule(lambda t: t % 2.5 < 1.0, 120.0, flap_limit=1000, resume_dwell=0.3))
    back = [t for t, _, kind in out if kind == safety.RECOVERED]
    assert back == pytest.approx([1.0, 3.5 + 0.3, 6.0 + 0.6, 8.5 + 0.9], abs=H / 2)
    t_end, mode, kind = out[-1]
    assert (mode, kind) == (LAND, safety.LAND_UNSETTLED)  # lost at 10 s, back at 11 s, would resume at 12.2 s
    assert t_end == pytest.approx(10.0 + 2.0, abs=H * 1.5)
    assert "not yet for the 1.2 s a resume needs after 4 recoveries" in safety.reason(kind, "leader", 4, 2.0, 0.3)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("limit,dwell", [(1, 0.0), (3, 0.5), (3, 0.0), (5, 0.1)])
def test_no_input_pattern_gives_more_than_flap_limit_recoveries_a_minute(seed: int, limit: int, dwell: float) -> None:
    """Random losses of random lengths (the bound is the rule's, whatever the input does): at most
    ``flap_limit`` recoveries within any 60 s, and a vehicle that flaps more ends in LAND."""
    rng = np.random.default_rng(seed)
    edges = np.cumsum(rng.uniform(0.05, 3.0, size=400))
    def pattern(t: float) -> bool:
        return int(np.searchsorted(edges, t)) % 2 == 1
    out = list(run_rule(pattern, 300.0, flap_limit=limit, resume_dwell=dwell))
    back = [t for t, _, kind in out if kind == safety.RECOVERED]
    assert most_recoveries_in_a_window(back) <= limit
    assert out[-1][1] == LAND  # these patterns flap (or hold) enough to land within 300 s


def test_losses_further_apart_than_the_window_recover_at_once_every_time() -> None:
    """An isolated loss recovers as it always did: losses 61 s apart never escalate nor wait."""
    out = list(run_rule(lambda t: t % 61.0 < 1.0 and t > 1.0, 61.0 * 8))
    back = [t for t, _, kind in out if kind == safety.RECOVERED]
    assert len(back) == 7 and all(t % 61.0 == pytest.approx(1.0) for t in back)
    assert all(mode != LAND for _, mode, _ in out)


def test_a_latched_hold_neither_recovers_nor_counts() -> None:
    mode, cause, latched, since, healthy, flaps, last, kind = safety.transition(
        FLYING, 0, False, 0.0, math.nan, 0, -math.inf, safety.SPEED, 1.0, 2.0, 3, 0.5)
    assert (mode, latched, kind) == (HOLD, True, safety.HELD)
    for t in (1.5, 2.9):
        mode, cause, latched, since, healthy, flaps, last, kind = safety.transition(
            mode, cause, latched, since, healthy, flaps, last, 0, t, 2.0, 3, 0.5)
        assert mode == HOLD and kind == safety.STAY and flaps == 0
    assert safety.transition(mode, cause, latched, since, healthy, flaps, last, 0, 3.0, 2.0, 3, 0.5)[-1] == \
        safety.LAND_HELD


def test_the_supervisor_lands_a_vehicle_whose_leader_flaps_and_says_why() -> None:
    """:class:`Supervisor` runs the rule: the measured 30 ms skew pattern, leader lost for 1.9 s
    and back for 0.6 s, lands the vehicle instead of a fifth cycle."""
    sup = Supervisor(mission({"resume_dwell": 0.0}), 1, (3, 4))
    k = 0
    while sup.mode in (FLYING, HOLD) and k < 100 * 60:
        step(sup, k, leader_silent=skewed(k * H))
        k += 1
    back = [e for e in sup.events if (e.src, e.dst) == (HOLD, FLYING)]
    assert [e.reason for e in back] == ["leader recovered"] * 3
    last = sup.events[-1]
    assert (last.src, last.dst) == (FLYING, LAND)
    assert last.reason.startswith("flapping: leader again after 3 recoveries from HOLD within 60 s")


# ------------------------------------------------------------------ one definition, compiled
TWINS = {"transition": "_transition", "hold_cause": "_hold_cause", "believe": "_believe", "silent": "_silent",
         "report_kind": "_report_kind"}
"""Each pure function of agent/safety.py's rule, and the name the twin compiles it under."""


FAILSAFE_TWINS = {"stopping_distance": "_stopping", "hold_reach": "_hold_reach", "anchor_axis": "_anchor_axis", "floored": "_floored",
                  "hold_axis": "_hold_axis", "saturation": "_saturation", "settled": "_settled"}
"""Each scalar core of tether/failsafe.py's laws (hold_point, hold, saturate, landed), and the name
the twin compiles it under."""


@pytest.mark.parametrize("name", sorted(TWINS))
def test_the_twin_compiles_the_supervisors_own_functions(name: str) -> None:
    """Not a copy: the compiled function's Python is agent.safety's function object itself."""
    twin = getattr(lockstep_kernel, TWINS[name])
    assert twin.py_func is getattr(safety, name)


def test_the_twin_compiles_the_supervisors_own_norm() -> None:
    """Not a copy: the twin's speed and error bounds run tether.vec.norm, the supervisor's."""
    from tether import vec

    assert lockstep_kernel._norm.py_func is vec.norm
    assert "sqrt" not in inspect.getsource(lockstep_kernel._ticks_py)  # no norm of its own beside it
    rng = np.random.default_rng(3)
    for d in (1, 2, 3, 4):
        for x in [rng.normal(size=d) * 10.0 ** rng.integers(-3, 4) for _ in range(200)] + [np.full(d, np.nan),
                                                                                          np.full(d, np.inf)]:
            assert same([lockstep_kernel._norm(x)], [vec.norm(x.tolist())]), x


def test_the_twin_assembles_the_laws_inputs_with_the_agents_own_functions() -> None:
    """Not a copy: the sample used for an in-neighbour, the weighted sums and kappa over the kept edges
    are agent.law's functions, compiled; the loop has no sum or extrapolation of its own beside them,
    and each agrees with the Python one bit for bit."""
    from agent import law

    assert lockstep_kernel._neighbour_axis.py_func is law.neighbour_axis
    assert lockstep_kernel._weighted_term.py_func is law.weighted_term
    assert lockstep_kernel._total.py_func is law.total
    src = inspect.getsource(lockstep_kernel._ticks_py)
    assert "0.5 * age * age" not in src and "w * pj" not in src and "+ w *" not in src
    rng = np.random.default_rng(5)
    for _ in range(300):
        x = rng.normal(size=6) * 10.0 ** rng.integers(-3, 4)
        age = float(rng.choice([0.0, 0.01, 0.2, np.nan]))
        for usable in (True, False):
            for comp in (True, False):
                args = (*x.tolist(), usable and age == age, age, comp)
                assert same(list(lockstep_kernel._neighbour_axis(*args)), list(law.neighbour_axis(*args))), args
        for k in (0, 1, 5):
            assert same([lockstep_kernel._weighted_term(k, *x[:3].tolist())], [law.weighted_term(k, *x[:3].tolist())])
        w = rng.random(4)
        assert same([lockstep_kernel._total(w)], [law.total(w.tolist())])


def test_the_twin_compiles_the_supervisors_own_graph_search() -> None:
    """Not a copy: the twin's reachability runs agent.safety's reaches_in, which the supervisor's
    graph (and so reaches) runs too."""
    assert lockstep_kernel._reaches_in.py_func is safety.reaches_in
    tree = ast.parse(textwrap.dedent(inspect.getsource(safety.Graph.reaches)))
    assert "reaches_in" in {node.func.id for node in ast.walk(tree)
                            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)}
    kernel_search = ast.parse(inspect.getsource(lockstep_kernel._reach_py))
    assert not any(isinstance(node, ast.While) for node in ast.walk(kernel_search))  # no second search


def closure(out: dict[int, list[int]], root: int, removed: set[int]) -> set[int]:
    """The nodes ``root`` reaches without ``removed``, grown to a fixed point (an oracle of another form)."""
    got = set() if root in removed else {root}
    while True:
        more = got | {b for a in got for b in out.get(a, ()) if b not in removed}
        if more == got:
            return got
        got = more


def test_the_compiled_graph_search_equals_the_supervisors_over_random_graphs() -> None:
    """Random directed graphs and removed sets: the compiled search, the Python one over arrays and
    reaches over the graph as a dict agree with a fixed-point closure on every pair."""
    rng = np.random.default_rng(5)
    for _ in range(300):
        n = int(rng.integers(1, 9))
        edges = sorted({(int(a), int(b)) for a, b in rng.integers(0, n, size=(int(rng.integers(0, 3 * n)), 2))})
        out: dict[int, list[int]] = {}
        for a, b in edges:
            out.setdefault(a, []).append(b)
        ptr = np.searchsorted([a for a, _ in edges], np.arange(n + 1), side="left").astype(np.int64)
        dst = np.array([b for _, b in edges], dtype=np.int64)
        removed = {int(x) for x in rng.integers(0, n, size=int(rng.integers(0, 3)))}
        gone = np.array([x in removed for x in range(n)])
        for root in range(n):
            for target in range(n):
                want = target in closure(out, root, removed)
                assert safety.reaches(out, root, target, removed) == want
                assert lockstep_kernel._reaches_in(ptr, dst, root, target, gone, np.zeros(n, dtype=np.bool_),
                                                   np.zeros(n, dtype=np.int64)) == want
                assert safety.reaches_in(ptr.tolist(), dst.tolist(), root, target, gone.tolist(), [False] * n,
                                         [0] * n) == want


@pytest.mark.parametrize("name", sorted(FAILSAFE_TWINS))
def test_the_twin_compiles_the_failsafe_laws_own_functions(name: str) -> None:
    """Not a copy: the compiled function's Python is tether.failsafe's function object itself."""
    twin = getattr(lockstep_kernel, FAILSAFE_TWINS[name])
    assert twin.py_func is getattr(failsafe, name)


FAILSAFE_CALLERS = {"hold_point": {"stopping_distance", "hold_reach", "anchor_axis", "floored"}, "hold": {"hold_axis", "saturate"},
                    "land": {"hold_axis", "saturate"}, "saturate": {"saturation"}, "landed": {"settled"}}
"""Which scalar cores each of tether/failsafe.py's laws calls: the laws the Python path flies are
made of the functions the twin compiles."""


@pytest.mark.parametrize("law", sorted(FAILSAFE_CALLERS))
def test_the_failsafe_laws_are_made_of_the_compiled_cores(law: str) -> None:
    tree = ast.parse(inspect.getsource(getattr(failsafe, law)))
    called = {node.func.id for node in ast.walk(tree) if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)}
    assert FAILSAFE_CALLERS[law] <= called


def same(a: Any, b: Any) -> bool:
    return all(x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y)) for x, y in zip(a, b)) \
        and len(a) == len(b)


def test_the_compiled_rule_equals_the_supervisors_over_random_states() -> None:
    """Random states, causes and times (NaN and infinite clocks included): the compiled functions
    give the Python's results, value for value."""
    rng = np.random.default_rng(7)
    modes = (FLYING, HOLD)
    times = (math.nan, -math.inf, 0.0, 0.5, 1.0, 2.0, 59.0, 61.0)
    for _ in range(3000):
        args = (int(rng.choice(modes)), int(rng.integers(0, len(safety.CAUSES))), bool(rng.integers(0, 2)),
                float(rng.choice(times)), float(rng.choice(times)), int(rng.integers(0, 6)),
                float(rng.choice(times)), int(rng.integers(0, len(safety.CAUSES))), float(rng.uniform(0.0, 80.0)),
                float(rng.choice((0.5, 2.0))), int(rng.integers(1, 5)), float(rng.choice((0.0, 0.5, 1.0))))
        assert same(lockstep_kernel._transition(*args), safety.transition(*args)), args
        flags = tuple(bool(x) for x in rng.integers(0, 2, size=7))
        assert lockstep_kernel._hold_cause(*flags) == safety.hold_cause(*flags)
        said = tuple(int(x) for x in rng.integers(0, 3, size=4)) + (int(rng.integers(1, 4)),)
        assert lockstep_kernel._believe(*said) == safety.believe(*said)
        age = float(rng.choice((math.nan, 0.0, 0.4, 0.6, 2.0)))
        t, timeout = float(rng.uniform(0.0, 2.0)), 0.5
        assert lockstep_kernel._silent(age, t, timeout) == safety.silent(age, t, timeout)
        code = int(rng.integers(-2, 8))
        assert lockstep_kernel._report_kind(code) == safety.report_kind(code)


ODD = (math.nan, math.inf, -math.inf, 0.0, -0.0, 5e-324, 1e-3, 0.05, 0.1, 1.0, 2.5, 1e200)


def test_the_compiled_failsafe_cores_equal_the_python_over_random_and_odd_values() -> None:
    """Random values and odd ones (NaN, infinities, signed zeros, the smallest and overflowing
    magnitudes): the compiled cores give the Python's results, bit for bit."""
    rng = np.random.default_rng(11)
    def value() -> float:
        return float(rng.choice(ODD)) if rng.random() < 0.3 else float(rng.normal(0.0, 3.0))
    for _ in range(3000):
        x = tuple(value() for _ in range(5))
        kp, max_accel = float(rng.choice((0.5, 1.0, 4.0))), float(rng.choice((0.5, 5.0, 10.0)))
        assert same([lockstep_kernel._hold_axis(*x)], [failsafe.hold_axis(*x)]), x
        assert same([lockstep_kernel._anchor_axis(*x[:3])], [failsafe.anchor_axis(*x[:3])]), x
        assert same([lockstep_kernel._floored(*x[:3])], [failsafe.floored(*x[:3])]), x
        speed, uu = abs(x[0]), x[1] * x[1]
        stop = failsafe.stopping_distance(speed, kp, max_accel)
        assert same([lockstep_kernel._stopping(speed, kp, max_accel)], [stop]), speed
        assert same([lockstep_kernel._hold_reach(speed, stop)], [failsafe.hold_reach(speed, stop)]), speed
        assert same([lockstep_kernel._saturation(uu, max_accel)], [failsafe.saturation(uu, max_accel)]), uu
        three = bool(rng.integers(0, 2))
        assert lockstep_kernel._settled(speed, x[2], abs(x[3]), abs(x[4]), three) == \
            failsafe.settled(speed, x[2], abs(x[3]), abs(x[4]), three)


RULE_STATE = {"land_after", "confirm", "flap_limit", "resume_dwell", "leader_timeout", "neighbour_timeout",
              "_SINCE", "_HEALTHY", "_LAST_FLAP", "_FLAPS", "_CAUSE", "_SAID", "_RUN",
              "max_accel", "p_hold", "land_settle", "held", "still", "STILL", "TOUCHDOWN"}
"""What only the rule's and the failsafe laws' own functions compare: a comparison of one of these
in the loop itself is the rule, HOLD's anchor, saturation or landing typed a second time."""

FAILSAFE_GAINS = {"hold_kp", "hold_kv", "max_accel", "ground"}
"""The failsafe laws' numbers: only their compiled cores do arithmetic with them."""


def arithmetic_names(tree: ast.AST) -> set[str]:
    """The names any arithmetic (a binary or unary operation) of ``tree`` reads."""
    return {node.id for op in ast.walk(tree) if isinstance(op, (ast.BinOp, ast.UnaryOp))
            for node in ast.walk(op) if isinstance(node, ast.Name)}


def test_the_loop_compares_nothing_of_the_rule_itself() -> None:
    """A transcription that reappears in ``_ticks_py`` fails here: the loop hands the rule's
    timeouts and state to the compiled functions and compares none of them itself."""
    tree = ast.parse(inspect.getsource(lockstep_kernel._ticks_py))
    compared = {node.id for cmp in ast.walk(tree) if isinstance(cmp, ast.Compare)
                for node in ast.walk(cmp) if isinstance(node, ast.Name)}
    assert not compared & RULE_STATE, sorted(compared & RULE_STATE)
    assert not arithmetic_names(tree) & FAILSAFE_GAINS, sorted(arithmetic_names(tree) & FAILSAFE_GAINS)
    called = {node.func.id for node in ast.walk(tree) if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)}
    assert set(TWINS.values()) | set(FAILSAFE_TWINS.values()) <= called


@pytest.mark.parametrize("line", [
    "if t - clock[i, _SINCE] >= land_after:\n    pass\n",  # the rule
    "if not norm <= max_accel:\n    pass\n",  # failsafe.saturate
    "if speed < still or held >= land_settle:\n    pass\n",  # failsafe.landed
    "if three and p_hold[i, d - 1] < ground:\n    pass\n",  # failsafe.hold_point's floor
])
def test_the_transcription_check_catches_a_retyped_rule(line: str) -> None:
    """The check above is not vacuous: the old hand-typed lines are caught."""
    tree = ast.parse(line)
    compared = {node.id for cmp in ast.walk(tree) if isinstance(cmp, ast.Compare)
                for node in ast.walk(cmp) if isinstance(node, ast.Name)}
    assert compared & RULE_STATE


@pytest.mark.parametrize("line", [
    "u[i, c] = -hold_kv * v[i, c] - hold_kp * (p[i, c] - p_hold[i, c])\n",  # failsafe.hold
    "scale = _stopping(speed, hold_kp, max_accel) / speed\n",  # failsafe.hold_point
    "scale = max_accel / norm\n",  # failsafe.saturate
])
def test_the_transcription_check_catches_retyped_failsafe_arithmetic(line: str) -> None:
    assert arithmetic_names(ast.parse(line)) & FAILSAFE_GAINS


# --------------------------------------------------------------------- an engine runs it
def flapping_leader(m: Any, seconds: float) -> Network:
    """Agent 1's link from the leader lost for 2.4 s (HOLD for 1.9 s, just under a land_after of 2 s), then
    back for 1.0 s, over and over: the measured flapping, on the link."""
    rules = []
    t = 1.0
    while t < seconds:
        rules += [LinkRule(profile=LinkProfile(loss=Bernoulli(p=1.0)), src=m.leader.id, dst=1, start=t),
                  LinkRule(profile="ideal", src=m.leader.id, dst=1, start=t + 2.4)]
        t += 3.4
    return Network(rules=tuple(rules))


@pytest.mark.parametrize("dwell", [0.0, 0.5])
def test_a_flapping_leader_link_lands_its_agent_in_both_lockstep_engines(dwell: float) -> None:
    """Lockstep, the compiled twin and the Python engine bit for bit: agent 1 recovers at most
    ``flap_limit`` times, then lands saying why (flapping; or, with the dwell, a resume that waits
    past land_after). Opened wide, the same link flaps it eleven times (the rule is what stops it)."""
    base = load_mission(builtin_path("section4"), 40.0)
    m = replace(base, netem=flapping_leader(base, 40.0),
                safety=replace(base.safety, resume_dwell=dwell, land_after=2.0))
    run = compiled_equals_python(m)
    ev = [e for e in run.safety.events if e.vehicle == 1 and e.src != e.dst]
    back = [e for e in ev if (e.src, e.dst) == (HOLD, FLYING)]
    assert 1 <= len(back) <= m.safety.flap_limit
    landing = next(e for e in ev if e.dst == LAND)
    if dwell == 0.0:
        assert (landing.src, len(back)) == (FLYING, 3) and landing.reason.startswith("flapping: leader again")
    else:
        assert landing.src == HOLD and "a resume needs" in landing.reason
    assert run.safety.safety_mode[-1, 0] == wire.LANDED

    wide = lockstep.simulate(replace(m, safety=replace(m.safety, flap_limit=1000, resume_dwell=0.0)))
    back_wide = [e for e in wide.safety.events if e.vehicle == 1 and (e.src, e.dst) == (HOLD, FLYING)]
    assert len(back_wide) >= 10 and not any(e.vehicle == 1 and e.dst == LAND for e in wide.safety.events)
