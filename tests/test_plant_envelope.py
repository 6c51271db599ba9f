"""The plant's watchdog as the last line of defence (pure): command stamps, the mission's envelope
(geofence, max_speed, max_accel) and the events it notes, whatever its agent sends."""

from __future__ import annotations

import math
import subprocess
import sys
import time
import uuid
from pathlib import Path

import msgspec
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import zenoh

from plant.watchdog import NOTE_EVERY, SATURATED_FOR, SPEED_RELEASE, Watchdog
from tether import catalog
from tether import mission as ms
from tether import transport as tp
from tether import wire
from tether.runfile import Run
from tether.wire import FLYING, HOLD, LAND, LANDED, MODES

H = 0.02
SAFETY = ms.Safety(land_after=2.0, cmd_cutoff=2.0)
"""The firmware's 2 s to LAND (shorter than the defaults, so that the landings fit these runs)."""
FENCE = msgspec.structs.replace(SAFETY, geofence=ms.Geofence(min=[-4.0, -4.0, 0.0], max=[4.0, 4.0, 3.0]))
FENCE_2D = msgspec.structs.replace(SAFETY, geofence=ms.Geofence(min=[-4.0, -4.0], max=[4.0, 4.0]))


class Point:
    """A point driven by the watchdog's output, integrated exactly (a double integrator)."""

    def __init__(self, p0: list[float], v0: list[float] | None = None):
        self.p = np.array(p0, dtype=float)
        self.v = np.zeros_like(self.p) if v0 is None else np.array(v0, dtype=float)

    def advance(self, u: list[float]) -> None:
        ua = np.asarray(u)
        self.p = self.p + self.v * H + 0.5 * H * H * ua
        self.v = self.v + ua * H


def fly(dog: Watchdog, veh: Point, k0: int, k1: int, command=None, mode: int = FLYING, events=None,
        track=None) -> list[int]:
    """Ticks k0..k1-1: the agent sends ``command(k)`` for tick k-1, stamped (k-1) H (None: silent)."""
    modes = []
    for k in range(k0, k1):
        if command is not None and (u := command(k)) is not None:
            dog.offer(u, (k - 1) * H, k - 1, k, mode)
        d = dog.step(k * H, veh.p, veh.v)
        assert np.all(np.isfinite(d.u)) and np.linalg.norm(d.u) <= dog.safety.max_accel * (1 + 1e-12)
        if events is not None:
            events.extend(d.events)
        veh.advance(d.u)
        if track is not None:
            track.append(veh.p.copy())
        modes.append(d.mode)
    return modes


# ----------------------------------------------------------------------------- stamps

@settings(max_examples=200, deadline=None)
@given(late=st.integers(1, 100), ahead=st.integers(0, 3))
def test_a_late_plant_flies_its_agents_newest_commands_and_still_holds_when_they_stop(late: int, ahead: int) -> None:
    """A plant ``late`` ticks behind its clock (catching up after a stall) takes the commands of the
    ticks its clock has reached, not beyond; when they stop, it holds once its clock is
    ``cmd_timeout`` past the newest: no later than it would on time, plus its lateness."""
    dog = Watchdog(SAFETY, 2, H)
    k_now, k_clock = 200, 200 + late
    k = k_clock + ahead
    taken = dog.offer([1.0, 0.0], k * H, k, k_now, k_clock=k_clock)
    assert taken == (ahead == 0)
    if not taken:
        assert dog.invalid == {"future": 1}
        return
    for step in range(k_now, k_now + 10_000):
        d = dog.step(step * H, [0.0, 0.0], [0.0, 0.0])
        if d.mode != FLYING:
            assert step * H - k * H > SAFETY.cmd_timeout - 1e-9  # never before the newest command is that old
            assert step * H - k * H <= SAFETY.cmd_timeout + H + 1e-9  # and within a tick of it
            return
    raise AssertionError("the watchdog never fired")


@settings(max_examples=300, deadline=None)
@given(k=st.integers(0, 2000), k_now=st.integers(1, 2000),
       skew=st.one_of(st.floats(-5.0, 5.0), st.sampled_from([0.0, 0.5, -0.5, 0.5001, 1e9, -1e9])))
def test_a_command_is_taken_only_if_its_stamp_is_its_ticks_and_the_plants_clock_allows_it(
        k: int, k_now: int, skew: float) -> None:
    """|t - k h| <= h/2, a tick no later than the plant's, not older than cmd_timeout: else dropped
    and counted by reason (``stamp``, ``future``, ``stale``), and an event."""
    dog = Watchdog(SAFETY, 2, H)
    stamp = k * H + skew * H
    taken = dog.offer([1.0, 0.0], stamp, k, k_now)
    ok_stamp = abs(stamp - k * H) <= 0.5 * H
    ok = ok_stamp and k <= k_now and k_now * H - stamp <= SAFETY.cmd_timeout
    older = ok and stamp < 0.0  # before the mission's start, which counts as a zero command's stamp: not newer
    assert taken == (ok and not older)
    if older:
        assert dog.invalid == {}
    elif not ok:
        reason = "stamp" if not ok_stamp else "future" if k > k_now else "stale"
        assert dog.invalid == {reason: 1}
        d = dog.step(k_now * H, [0.0, 0.0], [0.0, 0.0])
        noted = [e for e in d.events if e.src == e.dst]
        assert len(noted) == 1 and reason in noted[0].reason
        assert noted[0].wire(k_now, 2).reason.startswith("plant: ")
    assert dog.age(k_now * H) >= -0.5 * H  # a valid stamp is never more than h/2 ahead of the plant


def test_one_command_stamped_1e9_neither_shadows_later_commands_nor_stops_the_watchdog() -> None:
    """Measured in real time before this rule: plant 2 of section4 took it, dropped every later
    command as older, and its watchdog never fired (age negative for ever): 760 m at 83 m/s."""
    dog, veh, events = Watchdog(SAFETY, 2, H), Point([0.0, 0.0]), []
    fly(dog, veh, 1, 100, command=lambda k: [0.5, 0.0], events=events)
    assert not dog.offer([20.0, 0.0], 1e9, 99, 100)  # the forgery: the current tick, stamp 1e9
    assert dog.invalid == {"stamp": 1}
    modes = fly(dog, veh, 100, 200, command=lambda k: [0.0, 0.0], events=events)
    assert set(modes) == {FLYING} and dog.age(199 * H) == pytest.approx(H)  # every genuine one was taken
    assert [e.reason for e in events if "rejected" in e.reason] == ["command rejected (stamp: its stamp is not its tick's)"]
    modes = fly(dog, veh, 200, 240, events=events)  # the agent goes silent: the watchdog fires on time
    assert modes[math.ceil(SAFETY.cmd_timeout / H)] == HOLD


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.integers(-50, 400), st.floats(allow_nan=True, allow_infinity=True, width=64),
                          st.floats(-1e3, 1e3)), max_size=30))
def test_no_input_however_stamped_stops_the_watchdog_firing(offers: list[tuple[int, float, float]]) -> None:
    """Whatever commands came before (any tick, any stamp, any value), silence from tick 200 on
    holds the vehicle within cmd_timeout (plus a tick)."""
    dog, veh = Watchdog(SAFETY, 2, H), Point([0.0, 0.0])
    for j, (k, stamp, x) in enumerate(offers):
        dog.offer([x, 0.0], stamp, k, 200 if j % 2 else max(k, 0))
    fly(dog, veh, 1, 200, command=lambda k: [0.0, 0.0])
    modes = fly(dog, veh, 200, 200 + math.ceil(SAFETY.cmd_timeout / H) + 2)
    assert modes[-1] == HOLD


def test_a_flood_of_rejected_commands_is_one_event_a_second_with_its_count() -> None:
    dog, veh, events = Watchdog(SAFETY, 2, H), Point([0.0, 0.0]), []
    for k in range(1, 151):  # 3 s, 5 forgeries a tick, and the agent's genuine command
        for j in range(5):
            dog.offer([1.0, 0.0], k * H + 1.0 + j, k - 1, k)
        dog.offer([0.0, 0.0], (k - 1) * H, k - 1, k)
        d = dog.step(k * H, veh.p, veh.v)
        assert d.mode == FLYING
        events.extend(d.events)
    assert dog.invalid == {"stamp": 750}
    noted = [e for e in events if "rejected" in e.reason]
    assert len(noted) == math.ceil(3.0 / NOTE_EVERY)
    assert "250 commands rejected since 0.02 s" in noted[1].reason


# ----------------------------------------------------------------------------- envelope

def push(x: float):
    """The same command every tick, along x (2D or 3D by the caller's vehicle)."""
    return lambda k: [x, 0.0, 0.0]


def test_forged_commands_toward_the_fence_hold_then_land_inside_it() -> None:
    """An agent (or a forger) pushes at max_accel toward the fence and says FLYING: the plant
    holds when braking from here would reach the fence, latched (the push does not take it back),
    and lands after land_after; the vehicle never leaves the box."""
    dog, veh, events, track = Watchdog(FENCE, 3, H), Point([0.0, 0.0, 1.0]), [], []
    modes = fly(dog, veh, 1, 600, command=push(20.0), events=events, track=track)
    changes = [(MODES[e.src], MODES[e.dst]) for e in events if e.src != e.dst]
    assert changes[:3] == [("FLYING", "HOLD"), ("HOLD", "LAND"), ("LAND", "LANDED")]
    assert [e for e in events if e.src != e.dst][0].reason.startswith("geofence: would leave the box braking from here")
    hold_at = modes.index(HOLD)
    assert modes.index(LAND) - hold_at == pytest.approx(FENCE.land_after / H, abs=1)
    xs = np.array(track)[:, 0]
    assert xs.max() <= 4.0 and modes[-1] == LANDED
    assert abs(track[modes.index(LANDED)][2]) <= 0.05  # on the ground (then the point, no plant, drifts on)


def test_a_vehicle_outside_the_fence_lands_at_the_fence() -> None:
    """Found outside the box, pushed on outward: 3D, LAND about the nearest point of the box; 2D
    (LAND ends when still, as a vehicle braking back is at its turn), HOLD there first, latched,
    then LAND; either way it comes back to the fence and stops there."""
    dog, veh, events, track = Watchdog(FENCE_2D, 2, H), Point([5.0, 1.0], [2.0, 0.0]), [], []
    modes = fly(dog, veh, 1, 900, command=lambda k: [20.0, 0.0], events=events, track=track)
    assert modes[0] == HOLD and events[0].reason.startswith("geofence: outside")
    assert dog.p_hold == [4.0, 1.0] and LAND in modes
    assert modes[-1] == LANDED and np.linalg.norm(track[modes.index(LANDED)] - [4.0, 1.0]) < 0.1
    dog, veh, events, track = Watchdog(FENCE, 3, H), Point([5.0, 1.0, 2.0], [2.0, 0.0, 0.0]), [], []
    modes = fly(dog, veh, 1, 900, command=push(20.0), events=events, track=track)
    assert modes[0] == LAND and events[0].reason.startswith("geofence: outside")
    assert dog.p_hold == [4.0, 1.0, 2.0]
    down = track[modes.index(LANDED)]
    assert modes[-1] == LANDED and np.linalg.norm(down[:2] - [4.0, 1.0]) < 0.1 and down[2] < 0.05


def test_the_plant_leaves_a_fence_landing_to_an_agent_that_is_landing_already() -> None:
    """An honest agent whose own supervisor saw the breach first commands LAND: the plant's
    predicted-breach rule does not pre-empt it (lockstep runs are what the agent flies)."""
    dog, veh = Watchdog(FENCE, 3, H), Point([3.0, 0.0, 1.0], [3.0, 0.0, 0.0])
    modes = fly(dog, veh, 1, 5, command=lambda k: [-3.0, 0.0, 0.0], mode=LAND)
    assert set(modes) == {FLYING}


def test_beyond_max_speed_the_plant_brakes_whatever_its_agent_says() -> None:
    """Pushed on beyond max_speed: HOLD at once, braking at max_accel, never turning back; below
    SPEED_RELEASE max_speed it flies its (still pushing) agent again, and is braked again: the speed
    never goes beyond the limit by more than a tick or two of max_accel."""
    dog, veh, events, track = Watchdog(SAFETY, 2, H), Point([0.0, 0.0], [29.0, 0.0]), [], []
    modes = fly(dog, veh, 1, 300, command=lambda k: [20.0, 0.0], events=events, track=track)
    k = modes.index(HOLD)
    assert k <= 4 and [e for e in events if e.src != e.dst][0].reason.startswith("speed")
    speeds = np.linalg.norm(np.diff(np.array(track), axis=0), axis=1) / H
    assert speeds.max() <= SAFETY.max_speed + 2 * SAFETY.max_accel * H
    vx = np.diff(np.array(track)[:, 0]) / H
    knee = SAFETY.max_accel / math.sqrt(SAFETY.hold_kp)
    assert (vx[k:] >= 0.0).all()  # never back
    assert min(vx[k:]) >= min(SPEED_RELEASE * SAFETY.max_speed, knee) - 2 * SAFETY.max_accel * H  # released
    flown = [i for i in range(k, len(modes)) if modes[i] == FLYING]
    assert flown and HOLD in modes[flown[0]:]  # flown again, braked again
    assert LAND not in modes


@pytest.mark.parametrize("ticks, noted", [(4, False), (12, True)])
def test_a_command_at_max_accel_for_more_than_a_moment_is_an_event(ticks: int, noted: bool) -> None:
    dog, veh, events = Watchdog(SAFETY, 2, H), Point([0.0, 0.0]), []
    fly(dog, veh, 1, 1 + ticks, command=lambda k: [30.0, 0.0], events=events)
    fly(dog, veh, 1 + ticks, 20, command=lambda k: [-1.0, 0.0], events=events)
    reasons = [e.reason for e in events]
    assert dog.mode == FLYING and all(e.src == e.dst == FLYING for e in events)
    if noted:
        assert len(reasons) == 2 and reasons[0].startswith("command at max_accel 20 m/s^2 for 0.1")
        assert reasons[1].startswith("command back under max_accel after")
        assert SATURATED_FOR < (ticks - 1) * H
    else:
        assert reasons == []


# ----------------------------------------------------------------------------- ground

def test_ground_contact_while_flying_is_one_event_per_contact() -> None:
    dog, events = Watchdog(SAFETY, 3, H), []
    heights = [1.0, 0.5, 0.0, 0.0, 0.0, 0.01, 0.0, 0.1, 0.0, 0.0]  # two contacts (re-armed above 2 cm)
    for k, z in enumerate(heights, start=1):
        dog.offer([0.0, 0.0, 0.0], (k - 1) * H, k - 1, k)
        events.extend(dog.step(k * H, [0.0, 0.0, z], [0.0, 0.0, 0.0]).events)
    assert [e.t for e in events] == [3 * H, 9 * H]
    assert all(e.reason.startswith("ground contact while FLYING") for e in events)


def test_ground_contact_is_no_event_when_the_agent_is_landing_the_vehicle() -> None:
    dog = Watchdog(SAFETY, 3, H)
    dog.offer([0.0, 0.0, 0.0], 0.0, 0, 1, LAND)
    d = dog.step(H, [0.0, 0.0, 0.0], [0.0, 0.0, -0.1])
    assert d.mode == FLYING and d.rest == LAND and not d.events


# ----------------------------------------------------------------------------- real runs

REPO = Path(__file__).resolve().parent.parent


class Forger:
    """A Zenoh client of a real-time run's router that publishes forged commands on
    ``agent/<victim>/cmd`` (sender id and schema the victim's, as an insider or an --insecure
    network allows): ``forge(k, seq)`` gives the fields of the command to send when the victim's
    plant publishes tick ``k`` and the victim's newest real command has sequence number ``seq``
    (None: send nothing)."""

    def __init__(self, endpoint: str, ns: str, victim: int, forge):
        self.keys, self.victim, self.forge = wire.Keys(ns), victim, forge
        self.sent: list[wire.Command] = []
        self.seq = 0
        self.session = zenoh.open(tp.zenoh_config(tp.ZenohSettings(mode="client", connect=(endpoint,), lease=2.0,
                                                                   connect_timeout=30.0)))
        self.pub = self.session.declare_publisher(self.keys.topic("agent", victim, "cmd"))
        self.subs = [self.session.declare_subscriber(self.keys.topic("agent", victim, "cmd"), self._on_cmd),
                     self.session.declare_subscriber(self.keys.topic("plant", victim, "state"), self._on_state)]

    def _on_cmd(self, sample: zenoh.Sample) -> None:
        msg = wire.decode(sample.payload.to_bytes())
        if isinstance(msg, wire.Command) and msg not in self.sent:
            self.seq = max(self.seq, msg.seq)

    def _on_state(self, sample: zenoh.Sample) -> None:
        msg = wire.decode(sample.payload.to_bytes())
        if not isinstance(msg, wire.PlantState):
            return
        fields = self.forge(msg.k, self.seq)
        if fields is not None:
            cmd = wire.Command(sender=self.victim, **fields)
            self.sent.append(cmd)
            self.pub.put(wire.encode(cmd))

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


def attacked_run(tmp: Path, mission: str, duration: float, forge) -> tuple[Run, Path, list[wire.Command]]:
    """``tether run MISSION --clock realtime --insecure`` with a :class:`Forger` against vehicle 2."""
    port = tp.free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    ns = f"pe{uuid.uuid4().hex[:8]}"
    out = tmp / "run"
    cmd = [sys.executable, "-m", "cli", "run", mission, "--clock", "realtime", "--duration", str(duration),
           "--out", str(out), "--ns", ns, "--quiet", "--listen", ep, "--insecure"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    forger = None
    try:
        deadline = time.monotonic() + 60
        while forger is None:
            try:
                forger = Forger(ep, ns, 2, forge)
            except zenoh.ZError:
                assert proc.poll() is None and time.monotonic() < deadline, "the run's router never listened"
                time.sleep(0.2)
        _, err = proc.communicate(timeout=duration + 180)
    finally:
        if forger is not None:
            forger.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert (out / "run.npz").exists(), err[-3000:]
    return Run.load(out), out, forger.sent


@pytest.mark.slow
def test_a_command_stamped_1e9_is_rejected_by_the_plant_in_a_real_run(tmp_path: Path) -> None:
    """One command on agent/2/cmd for the agent's next tick, stamped 1e9, at 4 s of a real-time
    section4: plant 2 never flies it (contested or dropped: counted, logged, an event) and vehicle 2
    flies on in formation to the end."""
    h = 1.0 / ms.load(catalog.resolve("section4")).rate
    once = {"sent": False}

    def forge(k: int, seq: int):
        if once["sent"] or k * h < 4.0 or seq == 0:
            return None
        once["sent"] = True  # the agent's next tick, which it has not computed yet: it takes that tick's place
        return {"seq": seq + 2, "k": k + 1, "t": 1e9, "u": [0.0, 0.0]}

    run, out, sent = attacked_run(tmp_path, "section4", 10.0, forge)
    assert len(sent) == 1
    log = (out / "logs" / "plant-2.log").read_text()
    # the forgery takes the place of a tick the genuine agent then sends too: contested and flown as
    # none (plant/onboard.py), or, where it came alone, dropped by the watchdog's stamp rule
    assert ("command rejected (stamp" in log and "commands rejected by its watchdog" in log) or \
        "contested (two different commands for one tick): flown as none" in log, log[-2000:]
    assert run.runtime is not None
    col = int(np.nonzero(run.agent_ids == 2)[0][0])
    p = run.runtime.plant_p
    others = [c for c in range(p.shape[1]) if c != col]
    # with the others (it flew away to 760 m at 83 m/s without the rule; the diamond is 2 m wide)
    apart = np.nanmax(np.nanmin(np.linalg.norm(p[:, others] - p[:, col:col + 1], axis=-1), axis=1))
    assert apart < 5.0, apart


@pytest.mark.slow
def test_forged_commands_cannot_push_a_vehicle_through_the_plants_geofence(tmp_path: Path) -> None:
    """From 3 s of a real-time failsafe run (geofence x in [-4, 4]), u = (20, 0, 0) on agent/2/cmd
    every tick, stamped as the real ones, saying FLYING: plant 2 never leaves the box by more than a
    few ticks of motion, and holds and lands (the pushes contested, or the fence reached)."""
    m = ms.load(catalog.resolve("failsafe"))
    h = 1.0 / m.rate

    def forge(k: int, seq: int):
        if k * h < 3.0 or seq == 0:
            return None
        return {"seq": seq + 1, "k": k, "t": k * h, "u": [20.0, 0.0, 0.0]}

    run, out, sent = attacked_run(tmp_path, "failsafe", 12.0, forge)
    assert sent
    log = (out / "logs" / "plant-2.log").read_text()
    # beside the genuine agent, the pushes are contested and never flown (the plant holds, then lands);
    # a push that came alone is stopped by the plant's own geofence rule
    assert "geofence" in log or "commands mostly contested" in log, log[-2000:]
    assert run.runtime is not None
    col = int(np.nonzero(run.agent_ids == 2)[0][0])
    p = run.runtime.plant_p[:, col]
    fence = m.safety.geofence
    assert fence is not None
    assert np.nanmax(p[:, 0]) <= fence.max[0] + 0.25, np.nanmax(p[:, 0])
    modes = run.safety.plant_mode[:, col]
    assert LAND in modes.tolist() or LANDED in modes.tolist()
