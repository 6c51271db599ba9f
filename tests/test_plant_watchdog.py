"""The plant process's command watchdog with real processes and real Zenoh: a double-integrator
plant (``tether plant``) in real time driven by this test as its agent, which then falls silent
as a killed agent does (the plant sees only that its commands stop); and the operator's e-stop."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Literal

import numpy as np
import pytest
import zenoh

from tests import factories
from tests.support import wait_until
from tether import mission as ms
from tether import transport as tp
from tether import wire

pytestmark = pytest.mark.slow  # real plant processes left without commands for seconds

RATE = 50.0
H = 1.0 / RATE


def mission(tmp: Path, name: str, duration: float) -> Path:
    m = factories.build({
        "version": 1, "name": name, "dim": 3, "rate": RATE, "duration": duration,
        "law": {"kind": "benchmark", "kp0": 1.0, "kv0": 1.0, "gamma_p": 0.05, "gamma_v": 0.05},
        "leader": {"id": 2, "p0": [0.0, 0.0, 1.0]},
        "agents": [{"id": 1, "p0": [0.0, 0.0, 1.0], "v0": [0.0, 0.0, 0.0], "offset": [0.0, 0.0, 0.0]}],
        "edges": [{"from": 2, "to": 1, "weight": 1.0}]})
    path = tmp / f"{name}.toml"
    path.write_text(ms.dumps(m))
    return path


class Agent:
    """This test as agent 1 and operator: publishes the start, commands and safety commands; keeps
    every plant state it hears, with the wall time it heard it."""

    def __init__(self, session: zenoh.Session, keys: wire.Keys):
        self.keys = keys
        self.states: list[tuple[float, wire.PlantState]] = []
        self._lock = threading.Lock()

        def keep(sample: zenoh.Sample) -> None:
            msg = wire.decode(bytes(sample.payload))
            assert isinstance(msg, wire.PlantState)
            with self._lock:
                self.states.append((time.time(), msg))

        self._sub = session.declare_subscriber(keys.topic("plant", 1, "state"), keep)
        self._cmd = session.declare_publisher(keys.topic("agent", 1, "cmd"))
        self._start = session.declare_publisher(keys.start)
        self._safety = session.declare_publisher(keys.safety)
        self.seq = 0

    def snapshot(self) -> list[wire.PlantState]:
        with self._lock:
            return [m for _, m in self.states]

    def start(self, epoch: float) -> None:
        self._start.put(wire.encode(wire.Start(sender=0, seq=0, k=0, t=0.0, epoch=epoch)))

    def command(self, k: int, u: list[float]) -> None:
        self._cmd.put(wire.encode(wire.Command(sender=1, seq=self.seq, k=k, t=k * H, u=u)))
        self.seq += 1

    def forge(self, k: int, u: list[float]) -> None:
        """A copy of the command just sent, with another ``u``."""
        self._cmd.put(wire.encode(wire.Command(sender=1, seq=self.seq - 1, k=k, t=k * H, u=u)))

    def operator(self, action: Literal["land", "estop"]) -> None:
        self._safety.put(wire.encode(wire.SafetyCommand(sender=0, seq=0, k=0, t=0.0, action=action)))


def plant_process(path: Path, port: int, log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cli", "plant", "--id", "1", "--mission", str(path), "--clock",
                             "realtime", "--listen", f"tcp/127.0.0.1:{port}", "--lease", "1"],
                            stdin=subprocess.DEVNULL, stdout=log.open("w"), stderr=subprocess.STDOUT)


def fly(tmp: Path, name: str, duration: float, command_until: float,
        operator: tuple[float, Literal["land", "estop"]] | None = None,
        forge: tuple[float, float] | None = None) -> tuple[list[wire.PlantState], str]:
    """Run the plant for ``duration``: command u = (1, 0, -v_z) [m/s^2] each tick, half a period after
    the plant's, until ``command_until`` [s]; then silence. ``forge`` (from, until) [s]: meanwhile,
    after each command, a forger's copy of it with u = (20, 0, 0) (same tick, same number). Returns
    the states heard and the plant's log."""
    path = mission(tmp, name, duration)
    port = tp.free_tcp_port()
    log = tmp / f"{name}.log"
    proc = plant_process(path, port, log)
    try:
        with tp.open_session(tp.ZenohSettings(connect=(f"tcp/127.0.0.1:{port}",), connect_timeout=20.0)) as session:
            keys = wire.Keys(name)
            agent = Agent(session, keys)
            token = keys.token("plant", 1)
            wait_until(lambda: list(session.liveliness().get(token, timeout=0.5)), 60, "the plant's token")
            epoch = time.time() + 1.0
            agent.start(epoch)
            k_stop = round(command_until * RATE)
            sent = False
            for k in range(k_stop):
                due = epoch + (k + 0.5) * H
                while time.time() < due:  # pace the commands at the plant's rate, half a period after it
                    time.sleep(min(0.005, max(0.0, due - time.time())))
                states = agent.snapshot()
                vz = states[-1].vel[2] if states else 0.0
                agent.command(k, [1.0, 0.0, -2.0 * vz])
                if forge is not None and forge[0] <= k * H < forge[1]:
                    agent.forge(k, [20.0, 0.0, 0.0])
                if operator is not None and k == round(operator[0] * RATE):
                    agent.operator(operator[1])
            assert proc.wait(timeout=duration + 60) == 0, log.read_text()[-3000:]
            states = agent.snapshot()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return sorted(states, key=lambda s: s.k), log.read_text()


def test_a_silent_agents_plant_holds_within_cmd_timeout_then_lands(tmp_path: Path) -> None:
    s = ms.Safety()
    last = 3.0  # the agent's last command is that of tick 3 s - h
    states, log = fly(tmp_path, "wdsilent", 12.0 + s.cmd_cutoff - 2.0, last)  # lands after cmd_cutoff
    t = np.array([m.t for m in states])
    mode = np.array([m.mode for m in states])
    v = np.array([m.vel for m in states])
    p = np.array([m.p for m in states])
    last_cmd = last - H
    t_hold = t[np.argmax(mode == wire.HOLD)]
    t_land = t[np.argmax(mode == wire.LAND)]
    t_landed = t[np.argmax(mode == wire.LANDED)]
    print(f"\nlast command {last_cmd:.2f} s; HOLD at {t_hold:.2f} s (+{t_hold - last_cmd:.2f} s), LAND at "
          f"{t_land:.2f} s (+{t_land - last_cmd:.2f} s), LANDED at {t_landed:.2f} s (+{t_landed - last_cmd:.2f} s)")
    assert np.all(mode[t < last] == wire.FLYING)
    # HOLD within cmd_timeout + one tick of the last command: no open-loop flight beyond cmd_timeout
    assert s.cmd_timeout < t_hold - last_cmd <= s.cmd_timeout + H + 1e-9
    assert t_land - last_cmd >= s.cmd_cutoff and t_land - last_cmd <= s.cmd_cutoff + H + 1e-9
    speed = np.linalg.norm(v, axis=1)
    v_hold = speed[np.argmax(mode == wire.HOLD)]
    assert v_hold > 3.0  # it was flying at ~3.5 m/s along x
    # braking: HOLD's loop has both poles at -sqrt(hold_kp) (-1/s by default) and anchors the vehicle
    # where that brake brings it to rest, so the speed decays as v_hold e^{-t}: under 0.15 m/s after
    # ln(v_hold / 0.15) s (3.2 s from 3.5 m/s), and it stays under until LAND
    brake = math.log(v_hold / 0.15) / math.sqrt(s.hold_kp)
    braked = (t >= t_hold + brake + 0.2) & (t < t_land)
    assert braked.any() and np.all(np.linalg.norm(v[braked, :2], axis=1) < 0.15), speed[braked]
    # never faster after HOLD began than at its start; ends landed, at rest on the ground
    assert np.all(speed[t >= t_hold] <= v_hold + 1e-9)
    assert mode[-1] == wire.LANDED and abs(p[-1, 2] - s.ground) <= 0.02 and np.all(v[-1] == 0.0)
    assert np.all(p[:, 2] >= s.ground - 1e-9)
    assert "FLYING -> HOLD" in log and "HOLD -> LAND" in log and "LAND -> LANDED" in log


def test_operator_estop_cuts_thrust_and_the_vehicle_falls_to_the_ground(tmp_path: Path) -> None:
    states, log = fly(tmp_path, "wdestop", 6.0, 5.5, operator=(2.0, "estop"))
    t = np.array([m.t for m in states])
    mode = np.array([m.mode for m in states])
    p = np.array([m.p for m in states])
    k_e = int(np.argmax(mode == wire.ESTOP))
    assert 2.0 <= t[k_e] <= 2.0 + 0.5  # obeyed within a tick of hearing it
    assert np.all(mode[k_e:] == wire.ESTOP)
    fall = math.sqrt(2.0 * (p[k_e, 2] - 0.0) / 9.81)
    down = t[k_e:][p[k_e:, 2] <= 1e-9]
    assert down.size and down[0] - t[k_e] <= fall + 3 * H
    assert p[-1, 2] == 0.0 and "operator estop" in log


def test_two_commands_for_one_tick_are_flown_as_none_and_said(tmp_path: Path) -> None:
    """A forger copies each command with u = (20, 0, 0) for 1 s: every tick is contested, so neither
    command is flown (the vehicle never accelerates beyond the genuine 1 m/s^2 along x); the plant
    says so on its state (``plant: command of tick ... contested``), judges the stream suspect, holds
    after cmd_timeout, and flies again once the forgery has stopped and the stream is trusted."""
    s = ms.Safety()
    at, until = 2.0, 3.0
    states, log = fly(tmp_path, "wdforged", 7.0, 6.5, forge=(at, until))
    t = np.array([m.t for m in states])
    mode = np.array([m.mode for m in states])
    a = np.array([m.a for m in states])
    events = [(e.t, e.reason) for m in states for e in m.events]
    print(f"\nevents: {events}\nmax a_x {a[:, 0].max():.2f} m/s^2")
    assert a[:, 0].max() < 1.5  # the forged 20 m/s^2 never flown (nor max_accel); HOLD brakes backwards
    contested = [tt for tt, r in events if r.startswith("plant: command of tick") and "contested" in r]
    assert contested and at <= contested[0] <= at + 0.2
    assert any(r == "plant: commands mostly contested (a second sender on the key): none trusted" for _, r in events)
    assert all(r.startswith("plant: ") for _, r in events)
    hold = t[mode == wire.HOLD]
    assert len(hold) and at + s.cmd_timeout <= hold[0] <= until + s.cmd_timeout + 0.1
    assert mode[t < at].tolist() == [wire.FLYING] * int((t < at).sum())
    assert (mode[(t >= until + 1.0) & (t < 6.5)] == wire.FLYING).all()  # trusted again, commands back
    assert "contested" in log and "commands in conflict" in log
