"""A Crazyflie through cflib: a real vehicle (``radio://``, ``usb://``) or the software one
(``udp://``, ``python -m plant.cfsim``). The :class:`plant.base.Plant` of ``plant = "crazyflie"``.

Lifetime (:meth:`CrazyfliePlant.open` does 1-4; every step bounded by a timeout, cflib's own ``open_link`` has none):

1. **Connect** to the vehicle's URI and wait for ``fully_connected`` (TOCs cached in
   ``$XDG_CACHE_HOME/tether/cf-toc``, so later connections skip the TOC download).
2. **Log** ``stateEstimate.x/y/z/vx/vy/vz`` once a control tick (at most 100 Hz, cflib's fastest) and
   ``stateEstimate.ax/ay/az`` (world frame, in g) with ``supervisor.info`` every other tick, in two
   blocks (one block cannot hold nine floats: 26 bytes per packet; :func:`log_periods`: four vehicles
   at 100 Hz, eight at 50 Hz fit on one radio, ``docs/crazyflie.md``).
3. **Prepare** (:meth:`CrazyfliePlant._prepare`): with a fleet file (``tether/fleet.py``), set the
   vehicle type's firmware parameters, start its motion-capture feed (:mod:`plant.mocap`) and reset
   its estimator; then the pre-flight checks (:mod:`plant.preflight`): a refusal raises
   :class:`plant.preflight.PreflightRefused` naming the vehicle, before anything flies.
4. **Take off** with the high-level commander to ``takeoff_height`` and wait until there.
5. **Fly** one setpoint per control tick (100 Hz keeps the 500 ms watchdog fed):

   * ``mode = "attitude"`` (default): Eq. 4 turns the agent's ``u`` into thrust, roll and pitch
     (:func:`plant.quadrotor.eq4`, tilt limit, thrust limit) and ``send_setpoint(roll [deg],
     pitch [deg], yawrate [deg/s], thrust [0..65535])`` carries them. The thrust map is the
     firmware's battery-compensated one, ``pwm = T / (4 f_max) * 65535`` with ``f_max`` the motor
     thrust limit (0.1125 N for a CF 2.1). cflib negates the pitch it sends and the firmware's RPYT
     decoder negates it back from its legacy frame, so the right-handed angles of Eq. 4 go in as
     they are: positive pitch accelerates towards +x, positive roll towards -y. The yaw rate sent is
     0: the onboard attitude loop holds the yaw the vehicle took off with, which Eq. 4 takes to be
     ``yaw``. This is the paper's architecture (Fig. 2): the formation law is the outer
     loop, the vehicle's attitude controller the inner one, and nothing else closes a loop.
   * ``mode = "full_state"``: ``send_full_state_setpoint`` with the state one period ahead under
     ``u`` and ``u`` itself as the acceleration; the onboard position controller then adds its own
     position and velocity feedback around the law's (a different closed loop from the paper's:
     stiffer, but not Eq. 17 alone).

6. **Land** on exit, Ctrl-C or SIGTERM: notify the commander that low-level setpoints stop, land
   with the high-level commander, wait until down (bounded), stop, wait until the supervisor no
   longer counts it as flying (closing sooner lets the firmware's watchdog lock it on the ground:
   :meth:`CrazyfliePlant._wait_supervisor_landed`), close the link. Killed outright, the plant
   lands nothing itself: its guardian does (:mod:`plant.deadman`, armed at each take-off and
   disarmed once the vehicle is down or its motors are off). A vehicle its
   watchdog already landed (LANDED) or stopped (ESTOP) is not flown again.

The plant's command watchdog (:mod:`plant.watchdog`, run by the plant process) decides what each
setpoint carries: the agent's command (FLYING), or the watchdog's own HOLD and LAND commands, flown
through the same Eq. 4 (or full-state) setpoints while the agent is silent; in LANDED (touched
down) and ESTOP (operator) :meth:`CrazyfliePlant.step` sends ``send_stop_setpoint`` every tick:
motors off, and the firmware's 2 s watchdog stays fed, so it never locks a vehicle in the air.

**A vehicle its firmware takes out of the air** (``supervisor.info`` says tumbled, crashed or locked:
after a ground side stalled for 2 s the firmware cuts the motors and the vehicle falls) is down for
good (:meth:`CrazyfliePlant.down`, :func:`plant.preflight.down`): the watchdog goes to ESTOP, so its
agent lands and its neighbours drop it instead of following a vehicle lying on the floor whose agent
commands it up, and the plant sends only stop setpoints. A re-opened link that finds such a vehicle
on the ground does not take it off again.

**A link that goes quiet** (no state estimate for ``STALE_AFTER``) or **is lost** (cflib's
``connection_lost``/``connection_failed``) makes :meth:`CrazyfliePlant.state` raise
:class:`LinkLost`; the plant has no measurement then, so the watchdog holds and nothing new is
sent. On entering that state the plant asks the vehicle, best effort, to hold its last position
on its own (``send_notify_setpoint_stop`` + high-level ``go_to``: the onboard position
controller, which needs no link, instead of the firmware levelling out and cutting the motors
after 2 s). :meth:`CrazyfliePlant.recover` (a coroutine: every blocking cflib call runs in a
thread) waits ``RELINK_AFTER`` for a quiet link to speak again, then closes it and reconnects with
backoff (``RECONNECT_ATTEMPTS``, ``RECONNECT_BACKOFF`` doubled each time; every attempt logged).
A re-opened link that finds the vehicle on the ground and not stopped by its watchdog (it
restarted: a rebooted Crazyflie, or the software one killed and started again, thrust locked and
motors off) takes it off again from where it is, as at the start (:meth:`CrazyfliePlant._relaunch`);
one found in the air flies on. From before the link re-opens until that is decided and done, the
plant measures nothing and sends no low-level setpoint, though the re-opened link is healthy: its
agent cannot fly a restarted vehicle that is still on the ground.
Once the state estimate is back the watchdog flies the agent again if the agent has resumed, and
lands the vehicle otherwise. If every attempt fails, the plant process withdraws its liveliness
token (its agent holds, its neighbours count it out) and fails at the mission's end.

**A link that fails** (:class:`plant.radio.LinkMonitor`) and **a vehicle flying on motion capture
whose positions stop coming** (:func:`plant.mocap.fix_lost`: occluded or gone for
``plant.mocap.LOST_AFTER``; its estimator then drifts on the IMU) are not reconnected: the vehicle
holds for ``FAILED_HOLD`` and lands with its high-level commander (:meth:`CrazyfliePlant._hold_then_land`),
and the plant withdraws.

cflib's own ping thread is stopped once a link is up and the plant pings from a thread of its own
(:func:`_ping_instead`): cflib's thread can deadlock cflib's link-error handling, and with it every
setpoint after a lost link; the pings themselves stay, because a send is what finds a dead
``udp://`` endpoint at once (the closed port's ICMP error), before a vehicle restarted at the same
address could hear anything meant for the old one.

Closing a link that may still reach the vehicle never goes through cflib's ``close_link`` alone:
that sends ``send_setpoint(0, 0, 0, 0)``, zero thrust, which would drop a vehicle in flight.
"""

from __future__ import annotations

import logging
import math
import os
import struct
import threading
import time
from collections.abc import Callable
from typing import Any
from pathlib import Path

import numpy as np

from plant import deadman, preflight, radio
from plant.base import Sample
from plant.cfsim import motors
from plant.quadrotor import QuadrotorParams, eq4
from tether import mission as ms

log = logging.getLogger("tether")

_CF21 = QuadrotorParams()
G = _CF21.g
MOTOR_THRUST_MAX = _CF21.motor_thrust_max
"""Per-motor thrust at full command [N] (a Crazyflie 2.1's, with its source in ``plant.quadrotor``)."""
LOG_PERIOD_MS = 10
"""Shortest period of the position and velocity log block [ms] (100 Hz, cflib's fastest)."""


def log_periods(dt: float) -> tuple[int, int]:
    """The log blocks' periods [ms] for a plant ticking every ``dt`` [s]: position and velocity once a
    tick (never faster than :data:`LOG_PERIOD_MS`: a sample per tick is all the plant reads),
    acceleration every other tick. Four vehicles at 100 Hz or eight at 50 Hz fit on one radio (the
    radio budget in ``docs/crazyflie.md``, ``python bench/radio.py``)."""
    pv = max(LOG_PERIOD_MS, int(round(1000.0 * dt)))
    return pv, 2 * pv
STALE_AFTER = 1.0
"""A link whose state estimate has not come for this long [s] counts as down (100 log packets at
100 Hz; a loaded host can delay a few tens of them)."""
RELINK_AFTER = 4.0
"""A down link that cflib still holds open is given this long [s] to speak again (a radio fade, a
frozen simulator) before it is closed and reopened."""
RECONNECT_ATTEMPTS = 4
"""Reconnections tried before the plant gives the vehicle up."""
RECONNECT_BACKOFF = 0.25
"""Pause before the second attempt [s]; doubled before each further one."""


LINK_LIMITS = radio.LinkLimits()
"""When the link is worth a warning and when it fails (below 90 % of the log packets: a warning, as
Crazyswarm2 warns; below 50 %, or pings slower than 250 ms, for 4 s: failed)."""
LINK_WARN_EVERY = 5.0
"""Seconds between two messages about a degraded link (a link at the threshold would flap)."""
FAILED_HOLD = 1.0
"""How long [s] a vehicle whose link failed holds its position before it lands."""
FAILSAFE_REPEATS = 16
"""Copies of each order sent to a vehicle whose link failed (60 % of its packets lost: 1 in 3500 orders
lost)."""


class LinkLost(RuntimeError):
    """The vehicle's radio link is gone."""


def thrust_to_pwm(thrust: float, f_max: float = MOTOR_THRUST_MAX) -> int:
    """Collective thrust [N] -> the 16-bit ``send_setpoint`` thrust: the firmware's linear,
    battery-compensated map (:func:`plant.cfsim.motors.thrust_to_pwm`), rounded and clamped to
    0..65535."""
    return int(min(max(round(motors.thrust_to_pwm(thrust, f_max)), 0), motors.PWM_FULL))


def toc_cache() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    path = Path(base) / "tether" / "cf-toc"
    path.mkdir(parents=True, exist_ok=True)
    return path


class CrazyfliePlant:
    """One Crazyflie (see the module docstring). Real time only."""

    def __init__(self, m: ms.Mission, ids: list[int]):
        """No I/O: :meth:`open` connects and takes off."""
        if len(ids) != 1:
            raise ValueError("a crazyflie plant flies one vehicle")
        self.ids = tuple(ids)
        self.agent = m.agent(ids[0])
        if not isinstance(self.agent.plant, ms.CrazyfliePlant):
            raise ValueError(f"agent {ids[0]} does not fly a crazyflie plant")
        self.spec = self.agent.plant
        self._h = m.dt
        self._lock = threading.Lock()
        self._pos: np.ndarray | None = None
        """Newest position estimate [m; world frame], written by cflib's log thread under ``_lock``."""
        self._vel: np.ndarray | None = None
        """Newest velocity estimate [m/s; world frame]."""
        self._acc: np.ndarray | None = None
        """Newest acceleration estimate [m/s^2; world frame]."""
        self._supervisor: int | None = None
        """Newest ``supervisor.info`` bitfield, logged with the acceleration."""
        self._airborne = False
        """Taken off for this run (and not yet landed by :meth:`close`): :meth:`down` watches the firmware."""
        self._down_why: str | None = None
        """Why the firmware took the vehicle out of the air, once it has (:meth:`down`, for good)."""
        self._fresh = threading.Event()
        self._lost: str | None = None
        self._last_log = -math.inf
        self._landed = False
        self._stopped = False
        """Motors commanded off (LANDED or ESTOP): never flown again."""
        self._relinking = False
        """A reconnection is under way (:meth:`_reconnect`): from before the link re-opens until the
        vehicle is known to be in the air again, nothing is measured and nothing is sent."""
        self.relaunched = 0
        """Take-offs again after a re-opened link found the vehicle on the ground (it restarted)."""
        self._blind = False
        """The link went down and the vehicle was asked to hold on its own."""
        self.final_position: np.ndarray | None = None
        """Where the vehicle was when the link closed (after landing) [m]."""
        self.cf: Any = None
        """``cflib.crazyflie.Crazyflie`` once :meth:`_connect` ran (cflib ships no type information)."""
        self.monitor: radio.LinkMonitor | None = None
        """The link's delivery rate and ping round trip (:meth:`_watch_link`), from the logs' start."""
        self._link_said = (radio.OK, -math.inf)
        """The last warning's state and when it was logged (:meth:`_link_failed`)."""
        self._fleet_path = m.fleet
        self.vehicle: Any = None
        """The fleet's ``tether.fleet.Vehicle`` of this URI, once :meth:`open` read the fleet file."""
        self._fleet: Any = None
        self._mocap: Any = None
        """The running ``plant.mocap.MocapFeed`` of a vehicle that flies on motion capture."""
        self._no_fix: str | None = None
        """Why its motion-capture positions stopped coming, once they have (:meth:`_fix_lost`)."""
        self.health: Any = None
        """The pre-flight ``plant.preflight.Readings`` the take-off was allowed on."""

    def open(self, take_off: bool = True) -> "CrazyfliePlant":
        """Connect, start the logs, run the pre-flight checks and, with ``take_off``, take off (blocks
        until airborne; every wait bounded). Raises ``ConnectionError`` naming the URI,
        ``TimeoutError`` or :class:`plant.preflight.PreflightRefused`; the link is closed then.
        Without ``take_off`` the vehicle stays on the ground until :meth:`take_off`."""
        self._connect()
        try:
            self._prepare()
            if take_off:
                self._take_off()
        except BaseException:
            self._stop_mocap()
            self.cf.close_link()
            raise
        return self

    def take_off(self) -> None:
        """Take off to the plant's ``takeoff_height`` after :meth:`open` without it (blocks until
        airborne, at most ``takeoff_time + 5`` s; ``TimeoutError`` then, the vehicle still the
        plant's to land with :meth:`close`)."""
        self._take_off()

    # ------------------------------------------------------------------ lab: fleet, mocap, pre-flight
    @property
    def mass(self) -> float:
        """The vehicle's mass [kg] Eq. 4 uses: the fleet's for this vehicle, else the plant table's."""
        return float(self._fleet.mass_of(self.vehicle)) if self.vehicle is not None else self.spec.mass

    def _prepare(self) -> None:
        """Before take-off (blocks, bounded): the fleet's firmware parameters, its motion-capture feed
        and an estimator reset, if the mission names a fleet; then the pre-flight checks
        (:mod:`plant.preflight`). Raises :class:`plant.preflight.PreflightRefused` naming the vehicle."""

        uid, cf = self.ids[0], self.cf
        limits, settle = preflight.Limits(), 10.0
        name = f"crazyflie {uid} ({self.spec.uri})"
        if self._fleet_path is not None:
            from tether import fleet as fl

            self._fleet = f = fl.load(self._fleet_path)
            self.vehicle = v = f.by_uri(self.spec.uri)
            if v is None:
                raise preflight.PreflightRefused(f"{name}: no vehicle of the fleet {self._fleet_path} has this URI")
            name = f"crazyflie {uid} ({self.spec.uri}, fleet vehicle {v.name})"
            h = f.health
            limits, settle = preflight.Limits(h.battery_min, h.variance_max, h.link_min), h.settle_timeout
            vtype = f.type_of(v)
            for param, value in vtype.params.items():
                try:
                    cf.param.set_value(param, value)
                except (KeyError, AttributeError) as exc:
                    raise preflight.PreflightRefused(f"{name}: the firmware has no parameter {param} ({exc}); "
                                                     f"remove it from the fleet's type {v.type}") from None
            if vtype.position_source == "mocap":
                self._start_mocap(f, v)
            cf.param.set_value("kalman.resetEstimation", 1)  # the estimator clears it once reset
        readings = self._read_health(limits, settle)
        place = None if self.vehicle is None else (float(self.vehicle.p0[0]), float(self.vehicle.p0[1]),
                                                   float(self.vehicle.p0[2]))
        why = preflight.refusals(readings, limits, place)
        if why:
            raise preflight.PreflightRefused(f"{name} refused take-off: " + "; ".join(why))
        self.health = readings
        log.info("crazyflie %d: pre-flight passed (%.2f V, variance %.1e m^2, link %.0f %%)", uid, readings.vbat,
                 max(readings.variance), 100 * readings.link)

    def _start_mocap(self, f: Any, v: Any) -> None:
        from plant.mocap import MocapFeed

        cf = self.cf
        feed = MocapFeed(f.mocap.backend, f.mocap.hostname,
                         [(v.name, lambda p: cf.extpos.send_extpos(float(p[0]), float(p[1]), float(p[2])))],
                         options=f.mocap.options)
        self._mocap = feed.__enter__()
        log.info("crazyflie %d: motion capture %s %s feeds rigid body %s as extpos", self.ids[0], f.mocap.backend,
                 f.mocap.hostname, v.name)

    def _stop_mocap(self) -> None:
        if self._mocap is not None:
            self._mocap.__exit__(None, None, None)
            self._mocap = None

    def _read_health(self, limits: Any, settle: float) -> Any:
        """Log what the pre-flight checks need at 10 Hz until the estimator converged (or ``settle``
        [s] passed) and at least a second went by, pinging the vehicle meanwhile; the link is the
        share of those pings answered (:data:`HEALTH_PING_TAG`; a late answer counts, a lost one does
        not). Blocks, bounded by ``settle`` + 3 s."""
        import struct

        from cflib.crazyflie.log import LogConfig
        from cflib.crtp.crtpstack import CRTPPacket, CRTPPort

        period = 0.1
        block = LogConfig(name="tether_health", period_in_ms=int(period * 1000))
        for n in ("kalman.varPX", "kalman.varPY", "kalman.varPZ", "pm.vbat"):
            block.add_variable(n, "float")
        block.add_variable("pm.state", "int8_t")
        block.add_variable("supervisor.info", "uint16_t")
        got: list[dict[str, float]] = []
        came = threading.Event()

        def on_data(_stamp: int, data: dict[str, float], _block: Any) -> None:
            got.append(dict(data))
            came.set()

        block.data_received_cb.add_callback(on_data)
        try:
            self.cf.log.add_config(block)
        except KeyError as exc:
            raise preflight.PreflightRefused(f"crazyflie {self.ids[0]} ({self.spec.uri}): the firmware does not log "
                                             f"{exc}; pre-flight needs the Kalman estimator "
                                             "(stabilizer.estimator = 2)") from None
        answered: set[int] = set()

        def on_echo(pk: Any) -> None:
            if len(pk.data) == 9 and pk.data[0] == HEALTH_PING_TAG:
                answered.add(struct.unpack_from("<I", pk.data, 1)[0])

        self.cf.add_header_callback(on_echo, CRTPPort.LINKCTRL, 0)
        sent = 0
        t0 = time.monotonic()
        block.start()
        try:
            while True:
                self._check()
                ping = CRTPPacket()
                ping.set_header(CRTPPort.LINKCTRL, 0)
                ping.data = struct.pack("<BI4x", HEALTH_PING_TAG, sent)  # cflib's ping size: its handler reads 9
                self.cf.send_packet(ping)
                sent += 1
                now = time.monotonic()
                last = got[-1] if got else None
                ok = last is not None and preflight.converged(
                    (last["kalman.varPX"], last["kalman.varPY"], last["kalman.varPZ"]), limits)
                if (ok and now - t0 >= 1.0) or now - t0 >= settle + 1.0:
                    break
                came.clear()
                came.wait(period)
            deadline = time.monotonic() + HEALTH_PING_GRACE  # late answers count: a loaded host delays them
            while len(answered) < sent and time.monotonic() < deadline:
                came.clear()
                came.wait(0.05)
        finally:
            block.delete()
            self.cf.remove_header_callback(on_echo, CRTPPort.LINKCTRL, 0)
        link = len(answered) / sent
        if not got:
            return preflight.Readings(math.nan, -1, 0, (math.nan,) * 3, link)
        last = got[-1]
        with self._lock:
            p = None if self._pos is None else (float(self._pos[0]), float(self._pos[1]), float(self._pos[2]))
        return preflight.Readings(
            vbat=last["pm.vbat"], pm_state=int(last["pm.state"]), supervisor=int(last["supervisor.info"]),
            variance=(last["kalman.varPX"], last["kalman.varPY"], last["kalman.varPZ"]), link=link, position=p)

    def _connect(self) -> None:
        """Open the link and start the logs (blocks, bounded by ``connect_timeout`` twice). Raises
        ``ConnectionError`` naming the URI; the link is closed then."""
        import cflib.crtp
        from cflib.crazyflie import Crazyflie

        ids = self.ids
        cflib.crtp.init_drivers()
        cf = Crazyflie(rw_cache=str(toc_cache()))
        ready = threading.Event()
        cf.fully_connected.add_callback(lambda uri: ready.set())
        cf.connection_failed.add_callback(lambda uri, msg: self._on_lost(cf, f"connection failed: {msg}", ready))
        cf.connection_lost.add_callback(lambda uri, msg: self._on_lost(cf, f"connection lost: {msg}", ready))
        self.cf, self._lost = cf, None
        uri = self.spec.uri
        log.info("crazyflie %d: connecting to %s", ids[0], uri)
        cf.open_link(uri)
        try:
            if not ready.wait(self.spec.connect_timeout) or self._lost is not None:
                raise ConnectionError(f"agent {ids[0]}.plant.uri: {uri} did not connect within "
                                      f"{self.spec.connect_timeout:g} s ({self._lost or 'no answer'}); check the "
                                      "vehicle is on and the URI (radio channel, address, udp port)")
            _ping_instead(cf, lambda: self.cf is cf)
            self._start_logs()
        except BaseException:
            _drop_link(cf)
            raise

    # ------------------------------------------------------------------ link
    def _on_lost(self, cf: Any, why: str, ready: threading.Event) -> None:
        if cf is not self.cf:
            return  # a closed link's late news
        if self._lost is None:
            self._lost = why
            log.error("crazyflie %d: %s", self.ids[0], why)
        ready.set()
        self._fresh.set()

    def _check(self) -> None:
        if self._lost is not None:
            raise LinkLost(f"crazyflie {self.ids[0]} ({self.spec.uri}): {self._lost}")

    def _start_logs(self) -> None:
        from cflib.crazyflie.log import LogConfig

        pv_ms, acc_ms = log_periods(self._h)
        pv = LogConfig(name="tether_pv", period_in_ms=pv_ms)
        for n in ("x", "y", "z", "vx", "vy", "vz"):
            pv.add_variable(f"stateEstimate.{n}", "float")
        acc = LogConfig(name="tether_a", period_in_ms=acc_ms)
        for n in ("ax", "ay", "az"):
            acc.add_variable(f"stateEstimate.{n}", "float")
        acc.add_variable("supervisor.info", "uint16_t")  # 2 bytes more in a packet already sent: no airtime
        pv.data_received_cb.add_callback(self._on_pv)
        acc.data_received_cb.add_callback(self._on_acc)
        self._watch_link(1000.0 / pv_ms + 1000.0 / acc_ms)
        since = time.monotonic()
        self._fresh.clear()
        for block in (pv, acc):
            self.cf.log.add_config(block)
            block.start()
        if not self._wait_fresh(since, self.spec.connect_timeout):
            self._check()
            raise ConnectionError(f"agent {self.ids[0]}.plant.uri: {self.spec.uri} sends no state estimate "
                                  f"within {self.spec.connect_timeout:g} s; is a positioning system running?")

    def _wait_fresh(self, since: float, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not (self._last_log > since and self._pos is not None):
            if self._lost is not None or time.monotonic() > deadline:
                return False
            self._fresh.clear()
            self._fresh.wait(0.05)
        return True

    def _on_pv(self, timestamp: int, data: dict[str, float], block: Any) -> None:
        self._last_log = time.monotonic()
        with self._lock:
            if self.monitor is not None:
                self.monitor.packet(self._last_log)
            self._pos = np.array([data[f"stateEstimate.{n}"] for n in ("x", "y", "z")], dtype=float)
            self._vel = np.array([data[f"stateEstimate.{n}"] for n in ("vx", "vy", "vz")], dtype=float)
        self._fresh.set()

    def _on_acc(self, timestamp: int, data: dict[str, float], block: Any) -> None:
        with self._lock:
            if self.monitor is not None:
                self.monitor.packet(time.monotonic())
            self._acc = G * np.array([data[f"stateEstimate.{n}"] for n in ("ax", "ay", "az")], dtype=float)
            self._supervisor = int(data["supervisor.info"])

    def _wait_until(self, ready: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not ready():
            self._check()
            if time.monotonic() > deadline:
                raise TimeoutError(f"crazyflie {self.ids[0]}: {what} not done within {timeout:g} s")
            self._fresh.clear()
            self._fresh.wait(0.1)

    def _landed_seen(self) -> bool:
        """The last position estimate is on the ground (within 5 cm)."""
        with self._lock:
            return self._pos is not None and float(self._pos[2]) <= 0.05

    def _wait_supervisor_landed(self) -> None:
        """Wait, bounded by :data:`SUPERVISOR_LANDED_WAIT`, until the firmware's supervisor no longer
        counts the landed vehicle as flying (``supervisor.info`` bit 4).

        The supervisor counts a vehicle as flying for 2 s after its motors last ran. Closing the link
        sends a zero setpoint that takes the commander from the high-level planner, which was
        feeding it; if that setpoint ages past the commander watchdog's 0.5 s while the vehicle still
        counts as flying, the supervisor levels out and then locks it (a reboot before the next
        flight). Once it has left *flying*, the watchdog no longer acts. Firmware without
        ``supervisor.info`` gets the hysteresis waited out."""
        from cflib.crazyflie.log import LogConfig

        seen = threading.Event()
        block = LogConfig(name="tether_landed", period_in_ms=50)
        block.add_variable("supervisor.info", "uint16_t")
        block.data_received_cb.add_callback(
            lambda _stamp, data, _block: None if int(data["supervisor.info"]) & SUPERVISOR_IS_FLYING else seen.set())
        try:
            self.cf.log.add_config(block)
        except KeyError:
            time.sleep(SUPERVISOR_LANDED_WAIT)
            return
        try:
            block.start()
            if not seen.wait(SUPERVISOR_LANDED_WAIT):
                log.warning("crazyflie %d: the supervisor still counts it as flying %g s after landing",
                            self.ids[0], SUPERVISOR_LANDED_WAIT)
            block.delete()
        except Exception as exc:  # a link lost at the very end: the close goes on, said
            log.warning("crazyflie %d: could not watch the supervisor after landing: %s", self.ids[0], exc)

    def _take_off(self) -> None:
        sp = self.spec
        cmd = self.cf.commander
        cmd.send_notify_setpoint_stop()  # a previous session's low-level setpoints would block the planner
        cmd.send_setpoint(0.0, 0.0, 0.0, 0)  # unlock the RPYT thrust (locked at boot)
        log.info("crazyflie %d: taking off to %.2f m", self.ids[0], sp.takeoff_height)
        cmd.send_notify_setpoint_stop()
        self.cf.high_level_commander.takeoff(sp.takeoff_height, sp.takeoff_time)
        self._wait_until(lambda: self._pos is not None and self._pos[2] >= 0.9 * sp.takeoff_height,
                         sp.takeoff_time + 5.0, "take-off")
        log.info("crazyflie %d: airborne at %s", self.ids[0], np.round(self._position(), 3).tolist())
        self._airborne = True
        deadman.guardian(sp.land_time).arm(sp.uri)  # should this process die, a guardian lands it

    def _position(self) -> np.ndarray:
        """A copy of the newest position estimate; LinkLost if none came yet."""
        if self._pos is None:
            raise LinkLost(f"crazyflie {self.ids[0]} ({self.spec.uri}): no state estimate yet")
        return self._pos.copy()

    def _velocity(self) -> np.ndarray:
        if self._vel is None:
            raise LinkLost(f"crazyflie {self.ids[0]} ({self.spec.uri}): no state estimate yet")
        return self._vel.copy()

    # ------------------------------------------------------------------ the protocol
    # ------------------------------------------------------------------ link health
    def healthy(self) -> bool:
        """The link is up, fit to fly (:meth:`_link_failed`) and the state estimate fresh (not older than
        ``STALE_AFTER``)."""
        return (self._lost is None and time.monotonic() - self._last_log <= STALE_AFTER and not self._link_failed()
                and self._fix_lost() is None)

    def _fix_lost(self) -> str | None:
        """Why a vehicle flying on motion capture has lost its fix (:func:`plant.mocap.fix_lost`), for
        good once lost (the plant lands it, :meth:`recover`); None while positions come, or without
        motion capture."""
        if self._no_fix is None and self._mocap is not None and self.vehicle is not None:
            why = self._mocap.lost(self.vehicle.name, time.monotonic())
            if why is not None:
                self._no_fix = why
                log.error("crazyflie %d: %s", self.ids[0], why)
        return self._no_fix

    def down(self) -> str | None:
        """Why the firmware has taken this vehicle out of the air (:func:`plant.preflight.down`: it
        tumbled, crashed, or locked its motors after a watchdog cut, as when the ground side stalled
        for 2 s), for good once said; None while it flies, and before take-off, after the plant's own
        motors-off and once :meth:`close` lands it. The plant's watchdog then goes to ESTOP: its agent
        lands and its neighbours drop it, instead of flying on a vehicle lying on the floor."""
        if self._down_why is None and self._airborne and not self._stopped and not self._landed:
            with self._lock:
                bits = self._supervisor
            why = None if bits is None else preflight.down(bits)
            if why is not None:
                self._down_why = why
                log.error("crazyflie %d: down: %s", self.ids[0], why)
        return self._down_why

    def _watch_link(self, expected: float) -> None:
        """Count this link's log packets (``expected`` a second) and ping round trips from now on."""
        from cflib.crtp.crtpstack import CRTPPort

        mon = radio.LinkMonitor(expected, LINK_LIMITS)
        with self._lock:
            self.monitor = mon

        def pong(packet: Any) -> None:  # cflib's echo: (header 0, the sender's time.time()) as Latency.ping sends it
            data = bytes(packet.data)
            if len(data) == 9 and data[0] == 0:
                with self._lock:
                    mon.round_trip(time.monotonic(), time.time() - struct.unpack("<d", data[1:])[0])

        self.cf.add_header_callback(pong, CRTPPort.LINKCTRL, 0)

    def _link_failed(self) -> bool:
        """Judge the link (:class:`plant.radio.LinkMonitor`): log a warning when it degrades (again at most
        every :data:`LINK_WARN_EVERY`); True once it has failed, for good: the plant then lands the
        vehicle (:meth:`recover`)."""
        if self.monitor is None:
            return False
        now = time.monotonic()
        with self._lock:
            rep = self.monitor.judge(now)
        said, when = self._link_said
        if rep.state == radio.FAIL and said != radio.FAIL:
            self._link_said = (rep.state, now)
            log.error("crazyflie %d: link failed: %s (fails below %.0f %% or above %.0f ms for %g s)", self.ids[0],
                      rep.why, 100 * LINK_LIMITS.fail_rate, 1000 * LINK_LIMITS.fail_latency, LINK_LIMITS.fail_after)
        elif rep.state == radio.WARN and now - when >= LINK_WARN_EVERY:
            self._link_said = (rep.state, now)
            log.warning("crazyflie %d: link degraded: %s (warns below %.0f %%)", self.ids[0], rep.why,
                        100 * LINK_LIMITS.warn_rate)
        elif rep.state == radio.OK and said == radio.WARN and now - when >= LINK_WARN_EVERY:
            self._link_said = (rep.state, now)
            log.warning("crazyflie %d: link good again: %s", self.ids[0], rep.why)
        return rep.state == radio.FAIL

    def _hold_then_land(self) -> None:
        """A link no longer fit to fly: the vehicle holds its last position on its own for
        :data:`FAILED_HOLD`, then lands with its high-level commander (neither needs the link once
        heard; each order is sent :data:`FAILSAFE_REPEATS` times, since a failing link loses many);
        the plant sends it nothing more. Blocks, bounded."""
        sp, cmd, hl = self.spec, self.cf.commander, self.cf.high_level_commander
        with self._lock:
            p = None if self._pos is None else self._pos.copy()
        log.error("crazyflie %d: %s; holding %s, then landing, on its own", self.ids[0], self._down(),
                  None if p is None else np.round(p, 2).tolist())
        # from here on healthy() is False for good: step() sends nothing, the onboard commander flies
        for _ in range(FAILSAFE_REPEATS):
            # each hand-over at once followed by its order: a stopped planner heard alone offers motors off
            cmd.send_notify_setpoint_stop()
            if p is not None:
                hl.go_to(float(p[0]), float(p[1]), float(p[2]), sp.yaw, 1.0)
            time.sleep(0.02)
        time.sleep(FAILED_HOLD)
        for _ in range(FAILSAFE_REPEATS):
            hl.land(0.0, sp.land_time)
            time.sleep(0.02)
        deadline = time.monotonic() + sp.land_time + 5.0
        while time.monotonic() < deadline and self._lost is None and not self._stopped:
            with self._lock:
                self._stopped = self._pos is not None and self._pos[2] <= 0.05  # down: motors may stop
            time.sleep(0.05)
        if self._stopped:
            log.error("crazyflie %d: landed on its own (%s)", self.ids[0], self._down())
        else:  # close() then leaves it to its onboard commander, without a zero-thrust setpoint
            log.error("crazyflie %d: not seen on the ground within %g s of the order to land", self.ids[0],
                      sp.land_time + 5.0)

    def _down(self) -> str:
        if self._no_fix is not None:
            return self._no_fix
        if self.monitor is not None and self.monitor.failed is not None:
            return f"link failed: {self.monitor.failed.why}"
        if self._lost is not None:
            return self._lost
        return f"no state estimate for {time.monotonic() - self._last_log:.2f} s"

    def hold_blind(self) -> None:
        """Best effort, once per outage: ask the vehicle to hold its last known position with its
        own position controller (the high-level commander), which needs no link. Returns at once."""
        if self._blind or self._stopped or self.cf is None or self.cf.link is None or self._pos is None:
            return
        self._blind = True
        with self._lock:
            p = self._pos.copy()
        log.warning("crazyflie %d: link down (%s); asking the vehicle to hold %s on its own", self.ids[0],
                    self._down(), np.round(p, 2).tolist())
        self.cf.commander.send_notify_setpoint_stop()
        self.cf.high_level_commander.go_to(float(p[0]), float(p[1]), float(p[2]), self.spec.yaw, 1.0)

    async def recover(self) -> bool:
        """Bring a down link back (see the module docstring); True once the state estimate is fresh
        again, False when every reconnection failed. Never blocks the event loop."""
        import asyncio

        uid = self.ids[0]
        if self._no_fix is not None or (self.monitor is not None and self.monitor.failed is not None):
            # reconnecting mends no radio, and no motion capture
            await asyncio.to_thread(self._hold_then_land)
            return False
        self.hold_blind()
        deadline = time.monotonic() + RELINK_AFTER
        while self._lost is None and not self.healthy() and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        if self.healthy():
            log.warning("crazyflie %d: link back by itself", uid)
            self._blind = False
            return True
        pause = RECONNECT_BACKOFF
        for attempt in range(1, RECONNECT_ATTEMPTS + 1):
            log.warning("crazyflie %d: reconnecting to %s (attempt %d of %d; %s)", uid, self.spec.uri, attempt,
                        RECONNECT_ATTEMPTS, self._down())
            try:
                await asyncio.to_thread(self._reconnect)
            except (ConnectionError, TimeoutError, OSError, LinkLost) as exc:
                log.error("crazyflie %d: attempt %d failed: %s", uid, attempt, exc)
            else:
                log.warning("crazyflie %d: reconnected (attempt %d)", uid, attempt)
                self._blind = False
                return True
            if attempt < RECONNECT_ATTEMPTS:
                await asyncio.sleep(pause)
                pause *= 2.0
        self._lost = self._lost or "reconnection failed"
        log.error("crazyflie %d: gave up after %d reconnection attempts", uid, RECONNECT_ATTEMPTS)
        return False

    def _reconnect(self) -> None:
        """Close the present link without a zero-thrust setpoint and connect again (blocks, bounded);
        then take a vehicle found on the ground off again (:meth:`_relaunch`)."""
        # Set before the link re-opens: a re-opened link is healthy (fresh logs) before it is known
        # whether the vehicle restarted, and a sample or a setpoint in that gap would let the agent
        # fly a vehicle still on the ground.
        self._relinking = True
        try:
            _drop_link(self.cf)
            with self._lock:
                self._supervisor = None  # the re-opened link's own word on the firmware (:meth:`_relaunch`)
            self._connect()
            self._relaunch()
        finally:
            self._relinking = False

    def _relaunch(self) -> None:
        """After a re-opened link: a vehicle in the air flies on; one found on the ground and not
        stopped (it restarted: a rebooted Crazyflie, a software one killed and started again;
        its thrust is locked and its motors off) takes off again as at the start, from where it is,
        while :meth:`step` sends nothing. Blocks, bounded; raises ``TimeoutError`` or
        :class:`LinkLost` (then the next attempt, or the plant withdraws)."""
        sp = self.spec
        self._wait_until(lambda: self._pos is not None and self._vel is not None and self._supervisor is not None,
                         STALE_AFTER + 2.0, "a state estimate after reconnecting")
        with self._lock:
            p, v = self._position(), self._velocity()
        if self._stopped or p[2] >= 0.5 * sp.takeoff_height or float(np.linalg.norm(v)) > 0.3:
            return
        if self.down() is not None:  # not restarted: cut by its firmware while the link was down, still locked
            return
        log.warning("crazyflie %d: on the ground at %s after the link came back (the vehicle restarted): taking off "
                    "again", self.ids[0], np.round(p, 3).tolist())
        self._take_off()
        self.relaunched += 1

    def state(self) -> Sample:
        """The newest state estimate; raises :class:`LinkLost` while the link is down, and while a
        restarted vehicle takes off again (its agent keeps holding until it is back in the air)."""
        if self._relinking:
            raise LinkLost(f"crazyflie {self.ids[0]} ({self.spec.uri}): re-opening the link (a restarted vehicle "
                           "takes off again first)")
        if not self.healthy():
            raise LinkLost(f"crazyflie {self.ids[0]} ({self.spec.uri}): {self._down()}")
        with self._lock:
            p, v = self._position(), self._velocity()
            a = self._acc.copy() if self._acc is not None else np.zeros(3)
        return Sample(p[None], v[None], a[None], np.full((1, 3), np.nan))

    def step(self, u: np.ndarray, modes: list[int] | None = None) -> None:
        """Send the setpoint of the coming period (returns at once): ``u`` ``(1, 3)`` [m/s^2] in
        FLYING, HOLD and LAND (``modes``, one watchdog mode code; None: FLYING); motors off in
        LANDED and ESTOP. Nothing is sent while the link is down (:meth:`recover`)."""
        from tether.wire import ESTOP, LANDED

        if not self.healthy() or self._relinking:  # a take-off after a restart: the high-level commander flies
            return
        mode = modes[0] if modes is not None else 0
        if mode in (LANDED, ESTOP) or self._stopped:
            if not self._stopped:
                log.warning("crazyflie %d: motors off (%s)", self.ids[0], "landed" if mode == LANDED else "e-stop")
                deadman.guardian(self.spec.land_time).disarm(self.spec.uri)  # motors off stay off
            self._stopped = True
            self.cf.commander.send_stop_setpoint()
            return
        sp = self.spec
        u = np.asarray(u, dtype=float).reshape(-1)
        if sp.mode == "full_state":
            with self._lock:
                p, v = self._position(), self._velocity()
            h = self._h
            self.cf.commander.send_full_state_setpoint(
                (p + v * h + 0.5 * h * h * u).tolist(), (v + u * h).tolist(), u.tolist(),
                [0.0, 0.0, math.sin(sp.yaw / 2.0), math.cos(sp.yaw / 2.0)], 0.0, 0.0, 0.0)
            return
        thrust, roll, pitch, _ = eq4(u, sp.yaw, self.mass + sp.feedforward_mass, G, math.radians(sp.tilt_max),
                                     4.0 * MOTOR_THRUST_MAX)
        self.cf.commander.send_setpoint(math.degrees(roll), math.degrees(pitch), 0.0, thrust_to_pwm(thrust))

    def close(self) -> None:
        """Stop the setpoints and land (bounded waits), then close the link. Blocks (the plant
        process runs it in a thread). Idempotent. A vehicle whose motors are off stays down; one
        whose link is down cannot be landed (logged)."""
        if self._landed or self.cf is None:
            return
        self._landed = True
        try:
            if self._stopped:
                log.info("crazyflie %d: on the ground, motors off", self.ids[0])
            elif not self.healthy():
                log.error("crazyflie %d: cannot land: %s", self.ids[0], self._down())
            else:
                sp = self.spec
                cmd = self.cf.commander
                cmd.send_notify_setpoint_stop()
                log.info("crazyflie %d: landing", self.ids[0])
                self.cf.high_level_commander.land(0.0, sp.land_time)
                try:
                    self._wait_until(lambda: self._pos is not None and self._pos[2] <= 0.05, sp.land_time + 5.0,
                                     "landing")
                except (TimeoutError, LinkLost) as exc:
                    log.error("%s", exc)
                self.cf.high_level_commander.stop()
                self._wait_supervisor_landed()
        finally:
            self._stop_mocap()
            with self._lock:
                self.final_position = None if self._pos is None else self._pos.copy()
            if self._stopped or self._landed_seen():
                deadman.guardian(self.spec.land_time).disarm(self.spec.uri)
            if self._stopped or self.healthy():
                self.cf.close_link()  # its zero-thrust setpoint is harmless on the ground
            else:
                _drop_link(self.cf)


SUPERVISOR_IS_FLYING = 1 << 4
"""``supervisor.info``'s bit: the supervisor counts the vehicle as flying."""
SUPERVISOR_LANDED_WAIT = 3.0
"""How long [s] :meth:`CrazyfliePlant.close` waits for a landed vehicle's supervisor to stop counting
it as flying (the firmware's hysteresis is 2 s after the motors last ran)."""
HEALTH_PING_GRACE = 2.0
"""How long [s] the pre-flight waits after its last ping for answers still on their way: a late answer
(a loaded host, a simulator catching up) is an answer; only a lost one counts against the link."""
HEALTH_PING_TAG = 0x7E
"""First byte of the pre-flight's link pings (9-byte echo requests, as cflib's own latency pings, which
start with 0: cflib's echo handler reads every echo as ``<Bd`` and ignores other first bytes)."""
PING_PERIOD = 0.1
"""Seconds between the link pings the plant sends (cflib's own ping thread's period)."""


def _ping_instead(cf: Any, current: Callable[[], bool]) -> None:
    """Stop cflib's ping thread and ping from a thread of the plant's own, every
    :data:`PING_PERIOD`, while ``current()`` holds and the link is open.

    cflib handles a link error on whichever thread's send or receive meets it, inside
    ``Crazyflie.send_packet`` with its non-reentrant send lock held, and that handling joins cflib's
    ping thread: met on the ping thread itself, the join raises and the lock is never released; met
    on another sender while the ping thread waits for the lock, the join never returns. Either way
    every later setpoint blocks forever, and the plant's loop with it (seen once: a software
    Crazyflie killed mid-flight left its plant process wedged, neither flying nor withdrawn). cflib
    joins no thread it did not start, so the same pings (``Latency.ping``, an echo request
    the firmware answers) from this thread keep finding a dead link at once without that hazard."""
    cf.link_statistics.stop()

    def run() -> None:
        while current() and cf.link is not None:
            try:
                cf.link_statistics.latency.ping()
            except Exception as exc:  # a send on a dead link: cflib reports it through connection_lost
                log.debug("link ping: %s", exc)
                return
            time.sleep(PING_PERIOD)

    threading.Thread(target=run, name="tether-link-ping", daemon=True).start()


def _drop_link(cf: Any) -> None:
    """Close ``cf``'s link without cflib's parting ``send_setpoint(0, 0, 0, 0)`` (zero thrust: it
    would cut the motors of a vehicle in flight the moment it is heard) and stop its threads."""
    link = cf.link
    if link is not None:
        cf.link = None
        try:
            link.close()
        except Exception as exc:  # a driver that fails closing a dead link: nothing left to do
            log.debug("closing a dead link: %s", exc)
    cf.close_link()
