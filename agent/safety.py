"""The safety supervisor of one agent. Pure: no I/O, no clock; ``docs/safety.md`` is its manual.

Commands leave an agent only through :meth:`Supervisor.command`. Modes (codes in
:data:`tether.wire.MODES`), each change an event ``(tick, vehicle, from, to, reason)``:

=========  =====================================================================================
FLYING     the law's command (Eq. 17), saturated to ``max_accel``
HOLD       brake to zero velocity and come to rest where the brake stops the vehicle
           (:func:`tether.failsafe.hold` about :func:`anchor`)
LAND       hold horizontally, descend at ``land_speed`` to ``ground`` (:class:`tether.failsafe.Landing`)
LANDED     on the ground and still: a zero command, the plant rests (disarmed)
ESTOP      motors off: a zero command the plant obeys by cutting thrust (terminal)
=========  =====================================================================================

Transitions:

* FLYING → HOLD: the leader (for an agent that hears it) is silent for ``leader_timeout``; an
  in-neighbour is lost and the leader no longer reaches this agent in the surviving graph; the
  own speed is beyond ``max_speed`` (latched); the plant is silent; the agent was restarted into a
  running swarm and its inputs are not fresh yet (``Status.rejoining``: its first tick holds).
* HOLD → FLYING: the cause is gone (the leader is heard again, the graph reaches this agent
  again, the plant is back), unless it was latched; after recent recoveries, only once it has been
  gone ``resume_dwell`` times their number (:func:`transition`: no flapping).
* HOLD → LAND: held for ``land_after`` (the cause still there, or gone but not yet for the dwell).
* FLYING → LAND: a cause to hold after ``flap_limit`` recoveries, each within :data:`FLAP_WINDOW`
  of the last.
* FLYING/HOLD → LAND (or the configured action): the operator's ``land``; divergence
  (‖ξ‖ > ``max_formation_error``, a gain beyond ``gain_cap``, a non-finite command); a predicted
  geofence breach (the position plus the braking distance outside the box).
* FLYING/HOLD → LAND: the own plant reports LAND, LANDED or ESTOP (believed only as far as its
  samples agree, :class:`tether.gate.PlantModes`); never ESTOP on a report.
* FLYING → HOLD (then LAND after ``land_after``): the leader's or the own plant's stream is suspect
  (:attr:`Status.suspect`); a suspect in-neighbour is lost, as one silent.
* A neighbour's report that it does not fly is believed only once ``mode_confirm`` consecutive ticks
  say it, and its end once as many say FLYING again (:meth:`Supervisor.links`). A neighbour believed
  to HOLD is never a mode change: its edge is dropped when the leader still reaches this agent
  without it, else it is followed (an event): the law follows its actual motion. A neighbour believed
  to LAND, be LANDED or ESTOP is lost.
* LAND → LANDED: touched down and still (:func:`tether.failsafe.landed`); 2D: still, or held
  for ``land_settle``.
* any → ESTOP: the operator's ``estop`` (or ``estop`` as the configured action).

Losing an in-neighbour (its liveliness token gone, or silent for ``neighbour_timeout``) is not a
mode change while the leader still reaches this agent through the survivors (Assumption 1 on the
surviving graph, recomputed from the mission's graph and the liveliness this agent sees): the edge
is dropped and κ_i re-normalised over the remaining in-neighbours (an event records it); when the
neighbour is back, the edge is restored.

The rule between FLYING, HOLD and LAND and the weighing of neighbours' reports are pure functions of
scalars at the end of this module (:func:`transition`, :func:`hold_cause`, :func:`believe`,
:func:`silent`, :func:`report_kind`): :class:`Supervisor` calls them, and the in-process engine's
compiled twin (``sim/lockstep_kernel.py``) compiles these same functions with numba. Keep them to
what numba compiles (scalars, no strings, no containers).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, MutableSequence, Sequence
from dataclasses import dataclass

from tether import failsafe
from tether import vec
from tether.vec import Vec
from tether.mission import Mission, Safety
from tether.wire import ESTOP, FLYING, HOLD, LAND, LANDED, MODES, SafetyEvent


def reaches(out_edges: dict[int, list[int]], root: int, target: int, removed: Iterable[int] = ()) -> bool:
    """Whether ``root`` has a directed path to ``target`` in the graph without the ``removed`` nodes
    (:meth:`Graph.reaches`; a caller that asks again and again keeps the :class:`Graph`)."""
    return Graph(out_edges).reaches(root, target, removed)


class Graph:
    """A directed graph numbered once for :func:`reaches_in` (out-neighbours in compressed rows),
    with the search's scratch room: a supervisor builds it from the mission's edges at start and
    asks it whenever a neighbour is lost, never renumbering the graph per question."""

    def __init__(self, out_edges: dict[int, list[int]]):
        nodes = sorted(set(out_edges).union(*out_edges.values()))
        self.index = {node: x for x, node in enumerate(nodes)}
        self.out_ptr, self.out_dst = [0], []
        for node in nodes:
            self.out_dst += [self.index[nxt] for nxt in out_edges.get(node, ())]
            self.out_ptr.append(len(self.out_dst))
        self._seen, self._stack = [False] * len(nodes), [0] * len(nodes)

    def reaches(self, root: int, target: int, removed: Iterable[int] = ()) -> bool:
        """Whether ``root`` has a directed path to ``target`` without the ``removed`` nodes (a node
        of no edge reaches itself alone)."""
        removed = set(removed)
        if root in removed or target in removed:
            return False
        if root == target:
            return True
        if root not in self.index or target not in self.index:
            return False
        gone = [False] * len(self._seen)
        for node in removed:
            if node in self.index:
                gone[self.index[node]] = True
        return reaches_in(self.out_ptr, self.out_dst, self.index[root], self.index[target], gone, self._seen,
                          self._stack)


def reaches_in(out_ptr: Sequence[int], out_dst: Sequence[int], root: int, target: int, gone: Sequence[bool],
               seen: MutableSequence[bool], stack: MutableSequence[int]) -> bool:
    """Whether node ``root`` has a directed path to node ``target`` (nodes numbered from 0; node x's
    out-neighbours ``out_dst[out_ptr[x]:out_ptr[x + 1]]``) without the nodes ``x`` where ``gone[x]``.
    ``seen`` and ``stack``: room for one entry per node (overwritten). Lists or arrays: the
    in-process engine's compiled twin compiles this very function."""
    if gone[root] or gone[target]:
        return False
    for x in range(len(seen)):
        seen[x] = False
    top = 0
    stack[0] = root
    seen[root] = True
    while top >= 0:
        node = stack[top]
        top -= 1
        if node == target:
            return True
        for e in range(out_ptr[node], out_ptr[node + 1]):
            nxt = out_dst[e]
            if not seen[nxt] and not gone[nxt]:
                seen[nxt] = True
                top += 1
                stack[top] = nxt
    return False


@dataclass(frozen=True)
class Status:
    """What the agent process knows of its inputs at a tick, beyond the samples themselves.

    Attributes:
        gone: per in-neighbour (``law.neighbours`` order), its liveliness token is gone before it
            delivered this tick (real time; never in lockstep, where a tick waits for its inputs).
        modes: per in-neighbour, the mode its newest sample reports (a code of
            :data:`tether.wire.MODES`; FLYING when none is held). Believed only as far as consecutive
            ticks agree (:meth:`Supervisor.links`).
        others_gone: other nodes (agents, or the leader) whose tokens are gone, for the
            reachability of this agent: a gone leader reaches nobody.
        operator: the operator's last order, ``"land"``, ``"estop"`` or None.
        plant_silent: no fresh measurement from the own plant (its token is gone, or its newest
            sample is older than ``cmd_timeout``).
        plant_mode: the own plant's watchdog mode (a plant that has taken over to land is followed).
        rejoining: the agent was restarted into a running swarm and its inputs are not fresh yet
            (its own measurement or an in-neighbour's sample is missing or older than a period):
            it holds until they are (HOLD → FLYING "rejoin recovered"), or lands after ``land_after``.
        suspect: senders whose streams are suspect (:class:`tether.gate.Health`: mostly rejected, or
            in conflict with themselves): the own id (its plant's stream), the leader's, in-neighbours'.
    """

    gone: Sequence[bool] = ()
    modes: Sequence[int] = ()
    others_gone: frozenset[int] = frozenset()
    operator: str | None = None
    plant_silent: bool = False
    plant_mode: int = FLYING
    rejoining: bool = False
    suspect: frozenset[int] = frozenset()


NOMINAL = Status()


class Supervisor:
    """Agent ``agent_id``'s supervisor: its mode, why, and the events so far."""

    def __init__(self, m: Mission, agent_id: int, neighbours: Sequence[int]) -> None:
        self.cfg: Safety = m.safety
        self.agent_id = agent_id
        self.neighbours = tuple(neighbours)
        self.leader = m.leader.id
        self.hears_leader = self.leader in self.neighbours
        out_edges: dict[int, list[int]] = {}
        for e in m.edges:
            out_edges.setdefault(e.src, []).append(e.dst)
        self.graph = Graph(out_edges)
        """The mission's graph, numbered once for the reachability questions of every tick."""
        self.mode = FLYING
        self.cause = ""
        """Why the vehicle holds: ``speed``, ``plant``, ``leader``, ``unreachable`` or a latched reason."""
        self.latched = False
        self.healthy = math.nan
        """Since when HOLD's cause has been gone [s] (NaN: not holding, or the cause is there)."""
        self.flaps = 0
        """Recoveries from HOLD in the current run of them, each within :data:`FLAP_WINDOW` of the last."""
        self.last_flap = -math.inf
        """When the last recovery from HOLD was [s]."""
        self.missing: frozenset[int] = frozenset()
        """In-neighbours (agents) lost at the last tick, reachable or not."""
        self.since = 0.0
        """When the current mode (or HOLD's cause) began [s]."""
        self.p_hold: list[float] | None = None
        """Where HOLD and LAND keep the vehicle [m] (:func:`anchor`; None: not holding, or no finite position yet)."""
        self.lost: frozenset[int] = frozenset()
        """In-neighbours (agents) whose edges are dropped."""
        self.suspect: frozenset[int] = frozenset()
        """Senders whose streams were suspect at the last tick (:attr:`Status.suspect`)."""
        self.followed: frozenset[int] = frozenset()
        """In-neighbours believed to HOLD that are followed: the leader reaches this agent only through them."""
        m_in = len(self.neighbours)
        self.believed: list[int] = [REPORT_FLYING] * m_in
        """Per in-neighbour, what its mode reports are believed to say (:func:`report_kind`)."""
        self._said: list[int] = [REPORT_FLYING] * m_in
        self._run: list[int] = [0] * m_in
        self.events: list[SafetyEvent] = []
        """Every event so far."""
        self.diverged: SafetyEvent | None = None
        """The first divergence caught (the law's error, gains or command past their bounds)."""
        self._new: list[SafetyEvent] = []
        self._landing: failsafe.Landing | None = None
        """LAND's law and its memory (made at LAND's first tick; a vehicle lands once per run)."""

    # ------------------------------------------------------------------ inputs
    def links(self, k: int, t: float, ages: Sequence[float], status: Status) -> tuple[frozenset[int], bool, bool]:
        """Which in-neighbours' edges are dropped, whether the leader still reaches this agent, and
        whether the leader is silent (for an agent that hears it). Records edge drops and
        restorations, and the neighbours followed while they hold.

        An in-neighbour is *lost* when its token is gone, its stream is suspect, it is silent past
        ``neighbour_timeout``, or it is believed to LAND, be LANDED or ESTOP. One believed to HOLD is
        not lost: its edge is dropped too when the leader still reaches this agent without it (and
        without the lost ones), else it is *followed* (the law follows its actual motion: if it
        really holds still, this agent holds formation around it). A report is believed once
        ``mode_confirm`` consecutive ticks' samples say it (a silent neighbour reports nothing), so
        that a stream that alternates, forged reports between genuine ones, moves no belief."""
        cfg = self.cfg
        lost = set()
        holding = set()
        leader_silent = False
        if status.suspect != self.suspect:
            self._suspicion(k, t, status.suspect)
        for n, j in enumerate(self.neighbours):
            age = ages[n] if n < len(ages) else math.nan
            gone = bool(status.gone[n]) if n < len(status.gone) else False
            never = math.isnan(age)
            if j == self.leader:
                leader_silent = gone or silent(age, t, cfg.leader_timeout)
                continue
            quiet = gone or silent(age, t, cfg.neighbour_timeout)
            said = REPORT_FLYING if quiet or never or n >= len(status.modes) else report_kind(status.modes[n])
            self._said[n], self._run[n], self.believed[n] = believe(said, self._said[n], self._run[n],
                                                                    self.believed[n], cfg.mode_confirm)
            if quiet or j in status.suspect or self.believed[n] == REPORT_STOPPED:
                lost.add(j)
            elif self.believed[n] == REPORT_HOLD:
                holding.add(j)
        self.missing = frozenset(lost)
        removed = lost | set(status.others_gone)
        reachable = not removed or self.graph.reaches(self.leader, self.agent_id, removed)
        followed: frozenset[int] = frozenset()
        if reachable and holding:
            if self.graph.reaches(self.leader, self.agent_id, removed | holding):
                lost |= holding
            else:
                followed = frozenset(holding)
        new = frozenset(lost) if reachable else frozenset()
        if new != self.lost:
            self._event(k, t, self.mode, changes(sorted(new - self.lost), sorted(self.lost - new), EDGES))
            self.lost = new
        if followed != self.followed:
            self._event(k, t, self.mode, changes(sorted(followed - self.followed), sorted(self.followed - followed),
                                                 FOLLOWED))
            self.followed = followed
        return self.lost, reachable, leader_silent

    # ------------------------------------------------------------------ decision
    def command(self, k: int, t: float, p: Vec, v: Vec, u: Vec, xi: Vec, kp: Vec, kv: Vec, reachable: bool,
                leader_silent: bool, status: Status = NOMINAL) -> list[float]:
        """The command that leaves the agent at tick k (finite, norm <= ``max_accel``), given the
        law's ``u`` and errors (sequences of floats: lists, or numpy arrays). Moves the mode; the
        law's gains should advance only while the mode is FLYING (:attr:`flying`)."""
        cfg = self.cfg
        zero = [0.0] * len(p)
        if self.mode in (LANDED, ESTOP):
            if self.mode == LANDED and status.operator == "estop":
                self._go(k, t, ESTOP, "operator estop", p, v)
            return zero
        # orders and hard limits, strongest first
        if status.operator == "estop":
            self._go(k, t, ESTOP, "operator estop", p, v)
            return zero
        if status.operator == "land" and self.mode != LAND:
            self._go(k, t, LAND, "operator land", p, v)
        if status.plant_mode in (LAND, LANDED, ESTOP) and self.mode in (FLYING, HOLD):
            # the plant's watchdog has taken over (it never flies again): stop flying the law and land.
            # Never ESTOP on a report: only the operator and this supervisor's own checks cut motors
            self._go(k, t, LAND, f"plant reports {mode_name(status.plant_mode)}: not flying the law", p, v)
        if self.mode == FLYING or self.mode == HOLD:
            why = self._diverged(u, xi, kp, kv)
            if why is not None:
                self._act(k, t, cfg.divergence_action, why, p, v)
                if self.diverged is None:
                    self.diverged = SafetyEvent(k=k, t=t, vehicle=self.agent_id, src=FLYING, dst=self.mode, reason=why)
            elif (breach := self._fence_breach(p, v)) is not None:
                self._act(k, t, cfg.geofence.action if cfg.geofence is not None else "land", breach, p, v)
        if self.mode == ESTOP:
            return zero
        if self.mode in (FLYING, HOLD):
            speed = vec.norm(v)
            code = hold_cause(speed > cfg.max_speed, status.plant_silent, self.agent_id in status.suspect,
                              status.rejoining, leader_silent and self.hears_leader,
                              self.hears_leader and self.leader in status.suspect, reachable)
            held = CAUSES.index(self.cause) if self.cause in CAUSES else LATCHED
            mode, code_now, self.latched, _, self.healthy, self.flaps, self.last_flap, kind = transition(
                self.mode, held, self.latched, self.since, self.healthy, self.flaps, self.last_flap, code, t,
                cfg.land_after, cfg.flap_limit, cfg.resume_dwell)
            if code_now != held:
                self.cause = CAUSES[code_now]
            if kind == HELD:
                why = (f"speed {speed:.3g} m/s beyond max_speed {cfg.max_speed:g} m/s" if code == SPEED
                       else f"{listed(sorted(self.missing))} {UNREACHABLE}" if code == UNREACHABLE_CAUSE
                       else HOLD_WHY[code])
                self._go(k, t, mode, why, p, v)
            elif kind != STAY:
                self._go(k, t, mode, reason(kind, self.cause, self.flaps, cfg.land_after, cfg.resume_dwell), p, v)
        if self.mode == FLYING:
            out = failsafe.saturate(u, cfg.max_accel)
            if out is None:  # cannot be: a non-finite u in FLYING or HOLD is a divergence above, whose action
                # (hold, latched; land; estop) leaves FLYING for this tick; never pass it on if it ever were
                raise AssertionError(f"agent {self.agent_id}: a non-finite command reached FLYING at tick {k}")
            return out
        if self.p_hold is None:  # HOLD or LAND began on a position that was not finite: the first finite one
            if not all(map(math.isfinite, p)):
                return zero  # nowhere known to hold: no push anywhere (the measurement's gate keeps this rare)
            self.p_hold = anchor(cfg, p, v)
        if self.mode == HOLD:
            return failsafe.hold(p, v, self.p_hold, cfg.hold_kp, cfg.hold_kv, cfg.max_accel)
        # LAND
        if failsafe.landed(p, v, cfg.ground, t - self.since, cfg.land_settle):
            self._go(k, t, LANDED, failsafe.why_landed(p, v, t - self.since), p, v)
            return zero
        if self._landing is None:
            self._landing = failsafe.Landing(cfg.hold_kp, cfg.hold_kv, cfg.max_accel, cfg.land_speed, cfg.ground)
        return self._landing.command(t, p, v, self.p_hold)

    @property
    def flying(self) -> bool:
        return self.mode == FLYING

    def take_events(self) -> list[SafetyEvent]:
        """The events since the last call (for telemetry)."""
        out, self._new = self._new, []
        return out

    # ------------------------------------------------------------------ helpers
    def _diverged(self, u: Vec, xi: Vec, kp: Vec, kv: Vec) -> str | None:
        cfg = self.cfg
        err = vec.norm(xi)
        if not err <= cfg.max_formation_error:
            return f"divergence: |xi| {err:.3g} m beyond {cfg.max_formation_error:g} m"
        top = max(_max(kp), _max(kv))
        if not top <= cfg.gain_cap:
            return f"divergence: gain {top:.3g} beyond gain_cap {cfg.gain_cap:g}"
        if not math.isfinite(vec.dot(u, u)) and not all(map(math.isfinite, u)):
            return "divergence: non-finite command"
        return None

    def _fence_breach(self, p: Vec, v: Vec) -> str | None:
        fence = self.cfg.geofence
        if fence is None:
            return None
        cfg = self.cfg
        speed = vec.norm(v)
        # where the vehicle would stop if it braked now: HOLD's brake settles within about
        # 1/hold_kv seconds of travel at the current speed, more if saturated
        reach = speed / cfg.hold_kv + speed * speed / (2.0 * cfg.max_accel)
        ahead = [pc + (vc / speed) * reach for pc, vc in zip(p, v)] if speed > 0 and math.isfinite(reach) else p
        for where in (p, ahead):
            if not all(lo <= x <= hi for x, lo, hi in zip(where, fence.min, fence.max)):
                return "geofence: " + ("outside" if where is p else "would leave the box braking from here")
        return None

    def _suspicion(self, k: int, t: float, now: frozenset[int]) -> None:
        """An event (the mode unchanged) for streams that became suspect or are trusted again."""
        def name(j: int) -> str:
            return "own plant" if j == self.agent_id else "leader" if j == self.leader else f"neighbour {j}"

        new, back = sorted(now - self.suspect), sorted(self.suspect - now)
        words = []
        if new:
            words.append(f"suspected forgery or sensor fault: {', '.join(map(name, new))} "
                         "mostly rejected or in conflict with itself")
        if back:
            words.append(f"{', '.join(map(name, back))} trusted again")
        self._event(k, t, self.mode, "; ".join(words))
        self.suspect = now

    def _act(self, k: int, t: float, action: str, why: str, p: Vec, v: Vec) -> None:
        target = {"hold": HOLD, "land": LAND, "estop": ESTOP}[action]
        if target == HOLD:
            self.latched = True
            self.cause = why.split(":")[0]
        if self.mode != target:
            self._go(k, t, target, why, p, v)

    def _go(self, k: int, t: float, mode: int, why: str, p: Vec, v: Vec) -> None:
        if mode == self.mode:
            return
        if mode in (HOLD, LAND) and (self.p_hold is None or self.mode == FLYING):
            # never a made-up point (the origin would fly it across the arena): wait for a finite one
            self.p_hold = anchor(self.cfg, p, v) if all(map(math.isfinite, p)) else None
        self._event(k, t, mode, why)
        self.mode = mode
        self.since = t

    def _event(self, k: int, t: float, mode: int, why: str) -> None:
        ev = SafetyEvent(k=k, t=t, vehicle=self.agent_id, src=self.mode, dst=mode, reason=why)
        self.events.append(ev)
        self._new.append(ev)


# ---------------------------------------------------------------------- the pure rule
# HOLD's causes by code, strongest first (the order hold_cause tests them); LATCHED stands for a latched
# cause of another name (a divergence or a geofence whose action is hold), which never changes.
CAUSES = ("", "speed", "plant", "plant stream", "rejoin", "leader", "leader stream", "unreachable")
"""HOLD's causes by code (:attr:`Supervisor.cause`); code 0: none."""
SPEED, PLANT, PLANT_STREAM, REJOIN, LEADER, LEADER_STREAM, UNREACHABLE_CAUSE = range(1, len(CAUSES))
LATCHED = len(CAUSES)
HOLD_WHY = ("", "", "plant silent", "own plant's stream suspect (forgery or sensor fault)",
            "restarted into a running swarm: holding until every input is fresh", "leader silent",
            "leader's stream suspect (forgery or fault)", "")
"""What a HOLD event says of its cause (speed and unreachable are worded with their figures)."""

STAY, HELD, RECOVERED, LAND_HELD, LAND_UNSETTLED, LAND_FLAPPING = range(6)
"""What :func:`transition` did: nothing worth an event; FLYING → HOLD; HOLD → FLYING; HOLD → LAND
after ``land_after`` with the cause still there (or latched); HOLD → LAND after ``land_after`` with
the cause gone but not yet for the dwell a resume needs; FLYING → LAND instead of a HOLD that would
be one flap too many."""

FLAP_WINDOW = 60.0
"""Recoveries from HOLD each within this long [s] of the previous one count as one run of flaps."""


def hold_cause(fast: bool, plant_silent: bool, plant_suspect: bool, rejoining: bool, leader_silent: bool,
               leader_suspect: bool, reachable: bool) -> int:
    """The code (:data:`CAUSES`) of the strongest reason to hold, 0 for none: the own speed beyond
    ``max_speed``; the own plant silent, or its stream suspect; a rejoin with inputs not yet fresh;
    the leader silent or its stream suspect (for an agent that hears it); the leader not reaching
    this agent in the surviving graph. Pure; compiled as it is by the in-process engine's twin."""
    if fast:
        return SPEED
    if plant_silent:
        return PLANT
    if plant_suspect:
        return PLANT_STREAM
    if rejoining:
        return REJOIN
    if leader_silent:
        return LEADER
    if leader_suspect:
        return LEADER_STREAM
    if not reachable:
        return UNREACHABLE_CAUSE
    return 0


def transition(mode: int, cause: int, latched: bool, since: float, healthy: float, flaps: int,
               last_flap: float, why: int, t: float, land_after: float, flap_limit: int,
               resume_dwell: float) -> tuple[int, int, bool, float, float, int, float, int]:
    """One tick of the rule between FLYING, HOLD and LAND, for a vehicle FLYING or holding (HOLD)
    whose strongest reason to hold now is ``why`` (:func:`hold_cause`; 0: none) at time ``t`` [s].

    State in and out: the ``mode``, HOLD's ``cause`` (a code of :data:`CAUSES`, or
    :data:`LATCHED`) and whether it is ``latched``, ``since`` when the mode began [s], ``healthy``
    since when the cause has been gone while holding [s] (NaN: it is there), ``flaps`` the
    recoveries of the current run, ``last_flap`` the time of the last [s]; last, the ``kind`` of
    the change (:data:`STAY` ... :data:`LAND_FLAPPING`). The rule (``docs/safety.md``, *No flapping*):

    * FLYING with a cause: HOLD (latched for ``speed``); LAND instead when ``flap_limit``
      recoveries, each within :data:`FLAP_WINDOW` of the last, came before it.
    * HOLD, not latched, another cause: the cause changes; the clock to LAND runs on.
    * HOLD, not latched, the cause gone: FLYING once it has been gone ``resume_dwell`` times the
      recent recoveries (at once after none: an isolated loss recovers as it always did).
    * HOLD otherwise: LAND once held ``land_after``.

    Pure and scalar: the agents' supervisor calls it, and the in-process engine's twin compiles
    this very function (``sim/lockstep_kernel.py``)."""
    recent = flaps if t - last_flap <= FLAP_WINDOW else 0
    if mode == FLYING:
        if why == 0:
            return mode, cause, latched, since, healthy, flaps, last_flap, STAY
        if recent >= flap_limit:
            return LAND, why, False, t, math.nan, recent, last_flap, LAND_FLAPPING
        return HOLD, why, why == SPEED, t, math.nan, recent, last_flap, HELD
    if not latched and why != 0 and why != cause:
        return mode, why, latched, since, math.nan, flaps, last_flap, STAY
    if why == 0 and not latched:
        if healthy != healthy:
            healthy = t
        if t - healthy >= resume_dwell * recent:
            return FLYING, cause, False, t, math.nan, recent + 1, t, RECOVERED
        if t - since >= land_after:
            return LAND, cause, latched, t, healthy, recent, last_flap, LAND_UNSETTLED
        return mode, cause, latched, since, healthy, flaps, last_flap, STAY
    if t - since >= land_after:
        return LAND, cause, latched, t, math.nan, flaps, last_flap, LAND_HELD
    return mode, cause, latched, since, math.nan, flaps, last_flap, STAY


def reason(kind: int, cause: str, flaps: int, land_after: float, resume_dwell: float) -> str:
    """What the event of a :func:`transition` of ``kind`` other than :data:`HELD` says (``cause``:
    HOLD's, by name; ``flaps``: the recoveries it counted)."""
    if kind == RECOVERED:
        return f"{cause} recovered"
    if kind == LAND_HELD:
        return f"held for {land_after:g} s ({cause})"
    if kind == LAND_UNSETTLED:
        return (f"held for {land_after:g} s ({cause}): back, but not yet for the {resume_dwell * flaps:g} s "
                f"a resume needs after {flaps} recoveries within {FLAP_WINDOW:g} s of each other")
    return (f"flapping: {cause} again after {flaps} recoveries from HOLD within {FLAP_WINDOW:g} s of each "
            "other (flap_limit): landing instead of holding")


def believe(said: int, r_said: int, r_run: int, belief: int, confirm: int) -> tuple[int, int, int]:
    """A neighbour's mode report weighed (:meth:`Supervisor.links`): the kind ``said`` this tick
    (:func:`report_kind`), the kind said last (``r_said``) and for how many consecutive ticks
    (``r_run``), the kind believed; a kind is believed once ``confirm`` consecutive ticks say it.
    Returns the new ``(r_said, r_run, belief)``. Pure; the in-process engine's twin compiles it."""
    if said == r_said:
        r_run += 1
    else:
        r_said, r_run = said, 1
    if r_run >= confirm:
        belief = said
    return r_said, r_run, belief


def silent(age: float, t: float, timeout: float) -> bool:
    """Whether a sender whose newest sample is ``age`` old [s] (NaN: none yet) at time ``t`` [s] is
    silent: older than ``timeout``, or none past ``timeout`` into the run. Pure; compiled by the twin."""
    return age > timeout or (age != age and t > timeout)


def anchor(cfg: Safety, p: Vec, v: Vec) -> list[float]:
    """Where HOLD (and LAND) keeps a vehicle that begins it at ``p`` [m] moving at ``v`` [m/s]:
    where its brake brings it to rest (:func:`tether.failsafe.hold_point`, never below ``ground``
    in 3D). An anchor at ``p`` itself made a fast vehicle overshoot by its stopping distance and
    fly back through the one behind it. Where that point is outside the geofence box, the anchor
    is ``p`` brought into the box: the fence's prediction (:func:`tether.failsafe.fence_breach`)
    keeps a vehicle braking about ``p`` inside, and an anchor on the fence itself would be
    overshot. The plant's watchdog anchors its own HOLD and LAND the same way
    (:meth:`plant.watchdog.Watchdog.anchor`)."""
    p = vec.floats(p)
    out = failsafe.hold_point(p, vec.floats(v), cfg.hold_kp, cfg.max_accel, cfg.ground if len(p) >= 3 else None)
    fence = cfg.geofence
    if fence is None or all(lo <= x <= hi for x, lo, hi in zip(out, fence.min, fence.max)):
        return out
    return failsafe.inside(p, fence.min, fence.max)


REPORT_FLYING, REPORT_HOLD, REPORT_STOPPED = range(3)
"""What a neighbour's mode report says (:func:`report_kind`): it flies; it holds; it lands, has
landed or is e-stopped (or reports a mode that does not exist)."""


def report_kind(mode: int) -> int:
    """The kind of a neighbour's mode report: :data:`REPORT_FLYING`, :data:`REPORT_HOLD` or
    :data:`REPORT_STOPPED` (LAND, LANDED, ESTOP, or a code outside :data:`tether.wire.MODES`)."""
    return REPORT_FLYING if mode == FLYING else REPORT_HOLD if mode == HOLD else REPORT_STOPPED


EDGES = ("lost: edge dropped, kappa re-normalised", "back: edge restored")
"""What an event says of in-neighbours whose edges were dropped, and of those restored."""
FOLLOWED = ("holding, the only path from the leader: followed", "no longer followed as holding")
"""What an event says of holding in-neighbours followed, and of those no longer followed."""
UNREACHABLE = "lost and the leader no longer reaches this agent"


def listed(nbrs: Sequence[int]) -> str:
    """``neighbour 3`` or ``neighbours 2, 3``: how an event names in-neighbours."""
    return f"neighbour{'s' if len(nbrs) > 1 else ''} {', '.join(map(str, nbrs))}"


def changes(first: Sequence[int], second: Sequence[int], says: tuple[str, str]) -> str:
    """An event's reason for two sets of in-neighbours, each named with what ``says`` of it
    (:data:`EDGES`, :data:`FOLLOWED`); the in-process engine's compiled twin words its events with it."""
    return "; ".join(f"{listed(nbrs)} {what}" for nbrs, what in zip((first, second), says) if nbrs)


def _max(xs: Vec) -> float:
    """``ndarray.max()`` of a short list: NaN if any element is."""
    for x in xs:
        if x != x:
            return math.nan
    return max(xs)


def mode_name(code: int) -> str:
    return MODES[code] if 0 <= code < len(MODES) else f"mode {code}"
