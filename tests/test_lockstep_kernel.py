"""The in-process engine's compiled twin (sim/lockstep_kernel.py) against its Python tick, bit for bit,
and the batch forms it is built on: a link deciding many offers at once, a source's arrivals, a
disturbance bank's span of ticks."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from netem.channel import Link, batchable, link_rng
from netem.link import Channel
from plant.disturbance import DisturbanceBank
from sim import lockstep, lockstep_kernel, sweep
from tests.factories import build, random_mission
from tether import mission as ms
from tether import failsafe, wire
from agent import safety
from tether.catalog import builtin_path
from tether.inputs import Source
from tether.netprofile import Bernoulli, Corrupt, Delay, GilbertElliott, LinkProfile, LinkRule, Network, Rate, Reorder
from tether.node import load_mission
from tether.runfile import Run

pytest.importorskip("numba")

replace = msgspec.structs.replace


def assert_same_run(a: Run, b: Run) -> None:
    """Every array (events and link statistics included), byte for byte and dtype for dtype, and the meta."""
    x, y = a.arrays(), b.arrays()
    assert sorted(x) == sorted(y)
    for name in x:
        u, v = np.asarray(x[name]), np.asarray(y[name])
        assert u.dtype == v.dtype and u.shape == v.shape, name
        assert u.tobytes() == v.tobytes(), name
    assert a.meta == b.meta
    assert a.safety.events == b.safety.events


def short_failsafes(m: ms.Mission) -> ms.Mission:
    """``m`` with the firmware's 2 s from a lost input to LAND (the defaults wait 10 s, for a restart)."""
    return replace(m, safety=replace(m.safety, land_after=2.0, cmd_cutoff=2.0))


def compiled_equals_python(m: ms.Mission, **kw: object) -> Run:
    """The twin runs ``m`` itself (no fallback) and equals the Python engine; returns the twin's run."""
    fast = lockstep_kernel.simulate(m, **kw)  # type: ignore[arg-type]
    assert fast is not None, "the twin gave this run back to the Python engine: the mission does not test it"
    assert_same_run(fast, lockstep.simulate(m, engine="python", **kw))  # type: ignore[arg-type]
    return fast


# ------------------------------------------------------------------- the batch forms


def offers_one_by_one(link: Link, times: np.ndarray) -> np.ndarray:
    out = np.full(len(times), math.nan)
    for s, t in enumerate(times):
        copies = link.offer(float(t), b"x" * 40)
        assert len(copies) <= 1
        if copies:
            out[s] = copies[0].at
    return out


@pytest.mark.parametrize("prof", [
    LinkProfile(),  # the identity: draws nothing
    LinkProfile(loss=Bernoulli(p=0.3), delay=Delay(constant=0.05)),
    LinkProfile(loss=Bernoulli(p=1.0)),
    LinkProfile(delay=Delay(constant=0.2)),
    LinkProfile(loss=Bernoulli(p=0.999), delay=Delay(constant=0.013)),
    LinkProfile(loss=GilbertElliott(p=0.1, r=0.3)),  # bursts: one draw per offer (a certain loss draws none)
    LinkProfile(loss=GilbertElliott(p=0.9, r=0.95)),  # moves nearly every offer: states flip back and forth
    LinkProfile(loss=GilbertElliott(p=0.02, r=0.01, bad_loss=0.0, good_loss=1.0), delay=Delay(constant=0.1)),
    LinkProfile(loss=GilbertElliott(p=0.05, r=0.5, bad_loss=0.7, good_loss=0.02)),  # two draws per offer
    LinkProfile(loss=GilbertElliott(p=1.0, r=0.5, bad_loss=0.9)),  # a certain move out of the good state
    LinkProfile(loss=GilbertElliott(p=0.0, good_loss=0.0)),  # the identity, as a Gilbert-Elliott loss
    LinkProfile(delay=Delay(constant=0.03, jitter=0.02)),  # uniform jitter: samples overtake each other
    LinkProfile(loss=Bernoulli(p=0.2), delay=Delay(constant=0.05, jitter=0.04, distribution="pareto",
                                                    correlation=0.6)),
    LinkProfile(loss=GilbertElliott(p=0.1, r=0.2), delay=Delay(constant=0.01, jitter=0.5,
                                                                distribution="normal", correlation=0.9)),
])
def test_a_link_decides_many_offers_as_it_decides_them_one_by_one(prof: LinkProfile) -> None:
    assert batchable(prof)
    times = np.cumsum(np.random.default_rng(3).choice([0.0, 0.01, 0.02], size=700))  # repeated times too
    one, many = Link(prof, link_rng(7, 1, 2)), Link(prof, link_rng(7, 1, 2))
    want = offers_one_by_one(one, times[:500])
    got = np.concatenate([many.offer_times(times[:123]), many.offer_times(times[123:500])])
    assert want.tobytes() == got.tobytes()
    assert one.counts == many.counts and one.last_drop_reason == many.last_drop_reason
    assert one.last_offer == many.last_offer
    # the generators are left where the offers one by one leave them: what follows is the same
    assert offers_one_by_one(one, times[500:]).tobytes() == offers_one_by_one(many, times[500:]).tobytes()


def test_a_link_refuses_a_batch_it_cannot_decide_at_once_and_changes_nothing() -> None:
    for prof in (LinkProfile(duplicate=0.1), LinkProfile(delay=Delay(constant=0.05), reorder=Reorder(p=0.1)), LinkProfile(corrupt=Corrupt(p=0.1)),
                 LinkProfile(rate=Rate(bytes_per_s=1e4)), LinkProfile(outages=((1.0, 2.0),))):
        assert not batchable(prof)
        with pytest.raises(ValueError, match="batchable"):
            Link(prof, link_rng(1, 1, 2)).offer_times(np.array([0.0, 0.01]))
    logged = Link(LinkProfile(loss=Bernoulli(p=0.5)), link_rng(1, 1, 2), log=True)
    with pytest.raises(ValueError, match="decision log"):
        logged.offer_times(np.array([0.0]))
    link = Link(LinkProfile(loss=Bernoulli(p=0.5)), link_rng(1, 1, 2))
    link.offer(1.0, b"x")
    before = dict(link.counts)
    for bad in ([0.5, 2.0], [1.0, 0.9], [1.0, math.nan], [1.0, math.inf]):
        with pytest.raises(ValueError, match="non-decreasing"):
            link.offer_times(np.array(bad))
    assert link.counts == before and link.last_offer == 1.0


def test_a_channel_decides_across_its_profile_changes_as_send_does() -> None:
    """Loss then a delay that shrinks mid-run (later samples overtake earlier ones), then another loss:
    the times ``decide`` gives are those of ``send`` one message at a time (its decision log)."""
    net = Network(default=LinkProfile(loss=Bernoulli(p=0.2), delay=Delay(constant=0.25)),
                  rules=(LinkRule(profile=LinkProfile(delay=Delay(constant=0.02)), start=1.0),
                         LinkRule(profile=LinkProfile(loss=Bernoulli(p=0.6)), start=2.5, src=3)))
    m = replace(load_mission(builtin_path("section4"), 4.0), netem=net)
    times = np.arange(401) * m.dt
    for src in (3, 4):
        logged = Channel.of(replace(m, netem=replace(net, log=True)), src, 1)
        for t in times:
            logged.send(float(t), b"y" * 30)
        want = np.full(len(times), math.nan)
        for dec in logged.link.take_decisions():
            if dec.at is not None:
                want[dec.seq] = dec.at
        plain = Channel.of(m, src, 1)
        got = plain.decide(times)
        assert want.tobytes() == got.tobytes()
        assert plain.link.counts == logged.link.counts
        assert np.isnan(got).any() and not np.isnan(got).all()
    # times a send would refuse change nothing, even past a profile change
    plain = Channel.of(m, 3, 1)
    with pytest.raises(ValueError, match="non-decreasing"):
        plain.decide(np.array([0.0, 1.5, 3.0, 2.9]))
    assert plain.link.counts["offered"] == 0 and plain.decide(times).tobytes() == Channel.of(m, 3, 1).decide(times).tobytes()


def test_arrivals_are_what_a_source_behind_the_link_holds() -> None:
    """Each tick's newest sequence number and the stale, reordered and duplicate counts, against the
    runtime's own Source fed through a real Channel, with a delay that shrinks (reordering)."""
    net = Network(default=LinkProfile(loss=Bernoulli(p=0.3), delay=Delay(constant=0.3)),
                  rules=(LinkRule(profile=LinkProfile(loss=Bernoulli(p=0.1)), start=1.5),
                         LinkRule(profile=LinkProfile(delay=Delay(constant=3.5)), start=3.0),
                         LinkRule(profile=LinkProfile(), start=4.0)))
    m = replace(load_mission(builtin_path("section4"), 8.0), netem=net)
    times = np.arange(801) * m.dt
    at = Channel.of(m, 5, 1).decide(times)
    newest, received, stale, dup, reord = lockstep_kernel.arrivals(at, times)
    src = Source("5->1", wire.State, 5, keep=False, channel=Channel.of(m, 5, 1))
    held = []
    for k, t in enumerate(times):
        assert src.channel is not None
        src.channel.send(float(t), wire.encode(wire.State(sender=5, seq=k, k=k, t=float(t), p=[0.0, 0.0],
                                                          vel=[0.0, 0.0], a=[0.0, 0.0], mode=wire.FLYING)))
        src.deliver(float(t), wire.decode)
        held.append(-1 if src.newest is None else src.newest.seq)
    assert newest.tolist() == held
    assert (received, stale, dup, reord) == (src.received, src.stale, src.duplicates, src.reordered)
    assert reord > 0 and dup > 0  # both kinds of stale sample happened (3.5 s behind: beyond 256 ticks)


def test_a_banks_span_is_its_ticks_one_by_one() -> None:
    m = random_mission(np.random.default_rng(5), 3, disturbance="sinusoid", duration=30.0)
    bank, ref = DisturbanceBank.from_mission(m), DisturbanceBank.from_mission(m)
    value, dv, dp = bank.span(1000, 2600)  # crosses block edges
    for k in range(1000, 2600, 37):
        rdv, rdp = ref.increments(k)
        assert value[k - 1000].tobytes() == ref.value(k).tobytes()
        assert dv[k - 1000].tobytes() == rdv.tobytes() and dp[k - 1000].tobytes() == rdp.tobytes()


# ------------------------------------------------------------------- the twin against the Python tick


@pytest.mark.parametrize("law", ["sigma", "benchmark"])
@pytest.mark.parametrize("cell", [(0, 0, 1, 0), (10, 50, 1, 0), (30, 200, 1, 0), (50, 100, 1, 0),
                                  (30, 50, 5, 0), (50, 200, 5, 0), (10, 50, 1, 20), (30, 100, 5, 40)])
def test_section4_map_cells_equal_the_python_engine_bit_for_bit(law: str, cell: tuple[int, int, int, int]) -> None:
    """Loss [%], delay [ms], mean burst [messages] (Gilbert-Elliott beyond 1), uniform jitter [ms]."""
    loss, delay, burst, jitter = cell
    base = load_mission(builtin_path("section4"), 20.0)
    compiled_equals_python(sweep.point_mission(base, sweep.Point(law, loss, delay, burst), jitter_ms=jitter,
                                               duration=20.0))


@pytest.mark.parametrize("seed", range(6))
def test_random_missions_equal_the_python_engine_bit_for_bit(seed: int) -> None:
    """Random graphs, weights, offsets, disturbances, laws, feed-forwards, link policies and lossy
    delayed links whose profiles change mid-run, in 2D and 3D (the ground set far below)."""
    rng = np.random.default_rng(100 + seed)
    dim = 2 + seed % 2
    m = random_mission(rng, int(rng.integers(2, 7)), dim=dim, law=("sigma", "benchmark")[seed % 2],
                       disturbance=("sinusoid", "constant", "bounded_random", "none")[seed % 4], duration=6.0,
                       profile={"kind": "exp_accel", "a0": [0.3] * dim, "decay": 0.5} if seed % 3 == 0 else None)
    jitter = Delay(constant=0.04, jitter=0.03, distribution=("uniform", "normal", "pareto")[seed % 3], correlation=0.5)
    net = Network(default=LinkProfile(loss=Bernoulli(p=float(rng.uniform(0, 0.4))),
                                      delay=Delay(constant=float(rng.uniform(0, 0.15)))),
                  rules=(LinkRule(profile=LinkProfile(delay=Delay(constant=0.01)), start=2.0, dst=1),
                         LinkRule(profile=LinkProfile(loss=GilbertElliott(p=0.05, r=0.4), delay=jitter), start=3.0)))
    m = replace(m, netem=net if seed % 3 != 2 else None,
                law=replace(m.law, feedforward=("measured", "commanded", "none")[seed % 3]),
                links=ms.LinkPolicy(max_age=float(rng.choice([0.05, 0.5, math.inf])), compensate=bool(seed % 2)),
                safety=replace(m.safety, ground=-1e3))
    compiled_equals_python(m)
    compiled_equals_python(m, record=False)
    compiled_equals_python(m, duration=1.0)


def test_progress_never_goes_back_when_the_twin_gives_a_run_back() -> None:
    """The twin reports once, at its end; a run it gives back is reported by the Python engine alone."""
    m = load_mission(builtin_path("section4"), 100.0)
    seen: list[tuple[int, int]] = []
    lockstep.simulate(m, progress=lambda k, n: seen.append((k, n)))
    assert seen == [(m.steps, m.steps)]
    seen.clear()
    lockstep.simulate(m, progress=lambda k, n: seen.append((k, n)), diverge_at=0.05)  # given back at once
    assert seen and all(a[0] <= b[0] for a, b in zip(seen, seen[1:]))


# ------------------------------------------------------------------- HOLD and dropped edges


@pytest.mark.parametrize("cell", [(50, 100, 20), (40, 50, 30)])
def test_bursty_cells_whose_agents_hold_and_recover_equal_the_python_engine(cell: tuple[int, int, int]) -> None:
    """Long loss bursts silence the leader past leader_timeout: agent 1 holds, the ring behind it
    loses its path from the leader and holds too, and all fly on when the samples are back. With the
    flapping rule opened wide (``flap_limit`` 1000, no dwell) that is over a hundred mode changes a
    minute; the twin follows them itself, events and reasons included."""
    base = load_mission(builtin_path("section4"), 60.0)
    m = sweep.point_mission(base, sweep.Point("sigma", *cell), duration=60.0)
    run = compiled_equals_python(replace(m, safety=replace(m.safety, flap_limit=1000, resume_dwell=0.0)))
    reasons = {e.reason for e in run.safety.events}
    assert {"leader silent", "leader recovered", "unreachable recovered"} <= reasons
    assert any("no longer reaches" in why for why in reasons)
    assert (run.safety.safety_mode == wire.HOLD).any() and (run.safety.safety_mode == wire.FLYING).any()


@pytest.mark.parametrize("cell", [(50, 100, 20), (40, 50, 30)])
def test_bursty_cells_land_flapping_agents_as_the_python_engine_does(cell: tuple[int, int, int]) -> None:
    """The same cells with the default ``[safety]``: no agent recovers from HOLD more than
    ``flap_limit`` times within ``FLAP_WINDOW`` of each other; the next HOLD is a LAND saying why
    (or a HOLD whose resume waits past ``land_after`` lands), in the twin as in the Python engine."""
    base = load_mission(builtin_path("section4"), 60.0)
    m = sweep.point_mission(base, sweep.Point("sigma", *cell), duration=60.0)
    run = compiled_equals_python(m)
    limit = m.safety.flap_limit
    for vehicle in m.agent_ids:
        back = [e.t for e in run.safety.events if e.vehicle == vehicle and e.src == wire.HOLD and e.dst == wire.FLYING]
        assert all(b - a > safety.FLAP_WINDOW for a, b in zip(back, back[limit:])), (vehicle, back)
    reasons = [e.reason for e in run.safety.events if e.src != e.dst == wire.LAND]
    assert any(why.startswith("flapping: ") or "a resume needs" in why for why in reasons), reasons
    assert (run.safety.safety_mode[-1] == wire.LANDED).any()


def test_an_edge_dropped_and_restored_while_the_leader_still_reaches_equals_the_python_engine() -> None:
    """Agent 2 hears the leader and agent 1; its link from 1 is cut from 2 s to 3.5 s: the edge is
    dropped (kappa re-normalised over the leader alone) and restored, without a mode change."""
    raw = {
        "version": 1, "name": "drop", "dim": 2, "rate": 100.0, "duration": 6.0, "seed": 4,
        "law": {"kind": "sigma", "kp0": 2.0, "kv0": 2.0, "gamma_p": 0.05, "gamma_v": 0.05, "sigma": 0.5},
        "leader": {"id": 3, "p0": [0.0, 0.0], "v0": [0.0, 0.0], "profile": {"kind": "exp_accel", "a0": [0.5, 0.0],
                                                                             "decay": 0.2}},
        "agents": [{"id": 1, "p0": [1.0, 0.3], "offset": [1.0, 0.0],
                    "disturbance": {"kind": "sinusoid", "amplitude": [0.2, 0.1], "omega": [1.0, 2.0],
                                    "phase": [0.0, 1.0]}},
                   {"id": 2, "p0": [-1.0, 0.2], "offset": [-1.0, 0.0]}],
        "edges": [{"from": 3, "to": 1, "weight": 1.0}, {"from": 3, "to": 2, "weight": 0.5},
                  {"from": 1, "to": 2, "weight": 1.5}],
        "netem": {"default": {"delay": {"constant": 0.02}},
                  "rules": [{"from": 1, "to": 2, "start": 2.0, "profile": {"loss": {"kind": "bernoulli", "p": 1.0}}},
                            {"from": 1, "to": 2, "start": 3.5, "profile": {"delay": {"constant": 0.02}}}]},
    }
    m = build(raw)
    run = compiled_equals_python(m)
    assert [e.reason for e in run.safety.events] == ["neighbour 1 lost: edge dropped, kappa re-normalised",
                                                     "neighbour 1 back: edge restored"]
    assert (run.safety.safety_mode == wire.FLYING).all()


@pytest.mark.parametrize("seed", range(4))
def test_random_graphs_under_long_bursts_equal_the_python_engine(seed: int) -> None:
    """Random graphs with redundant paths: edges dropped while the leader still reaches, HOLD when it
    no longer does, recoveries."""
    rng = np.random.default_rng(300 + seed)
    m = random_mission(rng, int(rng.integers(3, 7)), law=("sigma", "benchmark")[seed % 2], disturbance="sinusoid",
                       duration=30.0)
    m = replace(m, netem=Network(default=LinkProfile(loss=GilbertElliott(p=0.02, r=0.04),
                                                     delay=Delay(constant=0.05))),
                safety=replace(m.safety, land_after=30.0, max_accel=1e3))
    run = compiled_equals_python(m)
    assert run.safety.events


# ------------------------------------------------------------------- runs given back to the Python engine


def given_back(m: ms.Mission) -> Run:
    """The twin gives up on ``m`` (None), and the default engine's run is the Python engine's."""
    assert lockstep_kernel.unsupported(m) is None
    assert lockstep_kernel.simulate(m) is None
    run = lockstep.simulate(m)
    assert_same_run(run, lockstep.simulate(m, engine="python"))
    assert_same_run(run, lockstep.simulate(m, engine="compiled"))
    return run


def test_an_orphan_held_past_land_after_lands_in_2d_as_in_the_python_engine() -> None:
    """Agent 3 hears nothing from agent 2 from t = 2 s: edge lost, the leader no longer reaches it,
    HOLD, LAND after land_after, LANDED (still, or held land_settle); its plant rests where it was, and
    agent 4 behind it loses it in turn. The twin follows every step, events worded as the supervisor's."""
    m = short_failsafes(load_mission(builtin_path("section4"), 16.0))
    net = Network(rules=(LinkRule(profile=LinkProfile(loss=Bernoulli(p=1.0)), start=2.0, src=2, dst=3),))
    run = compiled_equals_python(replace(m, netem=net))
    reasons = [e.reason for e in run.safety.events]
    assert any(why.startswith("held for 2 s (unreachable)") for why in reasons)
    assert any(why == "still" or why.startswith("landing held") for why in reasons)
    landed = run.safety.plant_mode[-1] == wire.LANDED
    assert landed.sum() >= 2  # agent 3, then agent 4 behind it
    rows = np.nonzero(run.safety.safety_mode[:, landed.argmax()] == wire.LANDED)[0]
    assert (run.v[rows[1]:, landed.argmax()] == 0.0).all()  # rests, reported still
    assert (np.diff(run.p[rows[1]:, landed.argmax()], axis=0) == 0.0).all()


@pytest.mark.parametrize("settle", [5.0, 0.2])
def test_a_silent_leader_lands_every_agent_in_2d_as_in_the_python_engine(settle: float) -> None:
    """Every agent lands: still (the default land_settle), or stopped after land_settle while its
    HOLD law still sways it (0.2 s)."""
    m = short_failsafes(load_mission(builtin_path("section4"), 12.0))
    lid = m.leader.id
    net = Network(rules=(LinkRule(profile=LinkProfile(delay=Delay(constant=0.8)), src=lid),))
    run = compiled_equals_python(replace(m, netem=net, safety=replace(m.safety, land_settle=settle)))
    reasons = [ev.reason for ev in run.safety.events]
    assert "leader silent" in reasons
    assert (run.safety.safety_mode[-1] == wire.LANDED).all()
    if settle < 1.0:
        assert any(why.startswith("landing held 0.20 s (land_settle), still moving at") for why in reasons)
    else:  # each still, or stopped by land_settle in the last centimetres before its anchor
        assert sum(why == "still" or why.startswith("landing held 5.00 s") for why in reasons) == 4


def test_a_hold_and_a_landing_at_speed_are_anchored_as_in_the_python_engine() -> None:
    """The leader lost at 15 s, the vehicles at about 8 m/s: each HOLD is anchored where its brake
    brings it to rest (failsafe.hold_point, compiled from its own stopping_distance), then 2D LAND
    and LANDED about that anchor; the twin's floats are the supervisor's, and no vehicle turns back."""
    m = short_failsafes(load_mission(builtin_path("section4"), 24.0))
    net = Network(rules=(LinkRule(profile=LinkProfile(loss=Bernoulli(p=1.0)), start=15.0, src=m.leader.id),))
    run = compiled_equals_python(replace(m, netem=net))
    dst = [ev.dst for ev in run.safety.events if ev.src != ev.dst]
    assert wire.HOLD in dst and wire.LAND in dst and wire.LANDED in dst
    k = int(np.argmax(run.safety.safety_mode[:, 0] == wire.HOLD))
    speed = float(np.linalg.norm(run.v[k, 0]))
    assert speed > 5.0  # at speed, as on a formation braking on an order
    rest = int(np.argmax(run.safety.safety_mode[:, 0] == wire.LANDED))
    along = (run.v[k:rest] * run.v[k]).sum(axis=-1)  # every vehicle's velocity along its own at HOLD
    assert (along >= -0.2 * speed).all()  # a sway at most (the disturbances), never back through the formation


def test_a_3d_hold_descending_at_speed_is_anchored_at_the_ground_as_in_the_python_engine() -> None:
    """3D, vehicles diving at 6 m/s three metres above the ground when the leader goes silent: the
    anchor's height is clamped to the ground (hold_point's floor), in the twin as in the supervisor."""
    m = random_mission(np.random.default_rng(5), 3, dim=3, duration=0.4)
    m = replace(m, agents=[replace(a, p0=[a.p0[0], a.p0[1], 1.0], v0=[3.0, 0.0, -6.0]) for a in m.agents],
                safety=replace(m.safety, ground=-2.0, land_after=5.0, leader_timeout=0.1),
                netem=Network(rules=(LinkRule(profile=LinkProfile(loss=Bernoulli(p=1.0)), start=0.05,
                                              src=m.leader.id),)))
    run = compiled_equals_python(m)
    holds = [ev for ev in run.safety.events if ev.dst == wire.HOLD]
    assert holds
    for ev in holds:  # braking from here would take it below the ground: the anchor's floor is used
        i = list(run.agent_ids).index(ev.vehicle)
        k = int(round(ev.t * m.rate))
        p, v = run.p[k, i].tolist(), run.v[k, i].tolist()
        assert failsafe.hold_point(p, v, m.safety.hold_kp, m.safety.max_accel)[2] < m.safety.ground
        assert failsafe.hold_point(p, v, m.safety.hold_kp, m.safety.max_accel, m.safety.ground)[2] == m.safety.ground


def test_a_3d_landing_is_left_to_the_python_engine() -> None:
    """In 3D, LAND descends with Landing's memory onto the ground: the twin gives the run back there."""
    m = random_mission(np.random.default_rng(12), 3, dim=3, duration=8.0)
    m = replace(m, agents=[replace(a, p0=[a.p0[0], a.p0[1], 3.0 + a.p0[2]]) for a in m.agents],
                safety=replace(m.safety, ground=-1.0, land_after=1.0),
                netem=Network(rules=(LinkRule(profile=LinkProfile(loss=Bernoulli(p=1.0)), start=1.0,
                                              src=m.leader.id),)))
    run = given_back(m)
    assert any(ev.dst == wire.LAND for ev in run.safety.events)


@pytest.mark.parametrize("bound", ["max_formation_error", "gain_cap", "max_speed", "max_accel"])
def test_a_safety_bound_reached_is_left_to_the_python_engine(bound: str) -> None:
    m = load_mission(builtin_path("section4"), 5.0)
    tight = {"max_formation_error": 0.5, "gain_cap": 2.0001, "max_speed": 0.2, "max_accel": 0.1}[bound]
    m = replace(m, safety=replace(m.safety, **{bound: tight}))
    if bound == "gain_cap":  # the benchmark law's gains only grow (Eq. 30)
        m = replace(m, law=replace(m.law, kind="benchmark", sigma=None))
    if bound == "max_accel":  # saturation is the nominal path: the twin scales the command itself
        compiled_equals_python(m)
        return
    run = given_back(m)
    assert run.safety.events


def test_a_run_past_diverge_at_is_left_to_the_python_engine() -> None:
    m = load_mission(builtin_path("section4"), 5.0)
    fast = lockstep_kernel.simulate(m, diverge_at=0.05)
    assert fast is None
    run = lockstep.simulate(m, diverge_at=0.05)
    assert_same_run(run, lockstep.simulate(m, engine="python", diverge_at=0.05))
    assert run.meta.diverged_at is not None


def test_a_3d_vehicle_through_the_ground_is_left_to_the_python_engine() -> None:
    m = random_mission(np.random.default_rng(9), 3, dim=3, duration=3.0)
    m = replace(m, agents=[replace(a, p0=[a.p0[0], a.p0[1], 0.05]) for a in m.agents],
                safety=replace(m.safety, ground=0.0))
    given_back(m)


@pytest.mark.parametrize("section", [
    {"netem": Network(default=LinkProfile(duplicate=0.05))},
    {"netem": Network(rules=(LinkRule(profile=LinkProfile(delay=Delay(constant=0.05), reorder=Reorder(p=0.2, gap=3)), start=1.0, src=2),))},
])
def test_a_mission_the_twin_does_not_know_runs_on_the_python_engine(section: dict) -> None:
    m = replace(load_mission(builtin_path("section4"), 3.0), **section)
    why = lockstep_kernel.unsupported(m)
    assert why is not None and "link" in why
    with pytest.raises(ValueError, match="compiled engine cannot run"):
        lockstep.simulate(m, engine="compiled")
    assert_same_run(lockstep.simulate(m), lockstep.simulate(m, engine="python"))


def test_vehicles_with_mass_are_not_compiled() -> None:
    m = load_mission(builtin_path("exp2"), 1.0)
    assert lockstep_kernel.unsupported(m) is not None
    with pytest.raises(ValueError, match="engine is"):
        lockstep.simulate(m, engine="fast")


def test_a_holding_neighbour_on_the_only_path_is_followed_as_in_the_python_engine() -> None:
    """The leader's samples to agent 1 are lost from 2 s to 3 s: agent 1 holds (leader silent) and
    flies again. Agent 2, whose only path from the leader is agent 1, believes the HOLD after
    ``mode_confirm`` ticks and follows agent 1 (an event, no mode change); agents 3 and 4 behind it
    fly on. The twin follows the reports' belief itself, events worded as the supervisor's."""
    m = load_mission(builtin_path("section4"), 8.0)
    net = Network(rules=(LinkRule(profile=LinkProfile(loss=Bernoulli(p=1.0)), start=2.0, src=5, dst=1),
                         LinkRule(profile=LinkProfile(), start=3.0, src=5, dst=1)))
    run = compiled_equals_python(replace(m, netem=net))
    events = [(e.vehicle, e.reason) for e in run.safety.events]
    assert events == [(1, "leader silent"), (2, "neighbour 1 holding, the only path from the leader: followed"),
                      (1, "leader recovered"), (2, "neighbour 1 no longer followed as holding")]
    held = [e for e in run.safety.events if e.vehicle == 1]
    followed = [e for e in run.safety.events if e.vehicle == 2]
    assert followed[0].k - held[0].k == m.safety.mode_confirm  # agent 1's HOLD is said from its next sample
    assert (run.safety.safety_mode[:, 1:] == wire.FLYING).all()
