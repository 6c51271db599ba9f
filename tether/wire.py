"""The wire: key expressions and messages every process speaks. Pure (no Zenoh, no I/O).

Keys (one scheme, also in ``docs/runtime.md``)::

    tether/<ns>/leader/<id>/state        State      the virtual leader's p, v, a at t_k
    tether/<ns>/agent/<id>/state         State      agent i's measured p, v, a at t_k (from its plant)
    tether/<ns>/agent/<id>/cmd           Command    u_i(t_k) for plant i
    tether/<ns>/agent/<id>/telemetry     Telemetry  xi, zeta, Kp, Kv, u, link and drop statistics
    tether/<ns>/plant/<id>/state         PlantState plant i's measurement at t_k (+ the true d, for records)
    tether/<ns>/agent/<id>/record        Record     lockstep, plant co-located in agent i: its plant samples and
                                                    telemetry of consecutive ticks, for the recorder
    tether/<ns>/clock/0/tick             Tick       lockstep: ticks up to ``grant`` may run
    tether/<ns>/<role>/<id>/ack          Ack        lockstep: ``<role> <id>`` has finished every tick up to k
    tether/<ns>/control/0/start          Start      real time: the common start instant
    tether/<ns>/control/0/recorded       Recorded   lockstep: the recorder holds every sample up to tick k;
                                                    the producers may close their sessions
    tether/<ns>/control/0/safety         SafetyCommand  operator: land every vehicle, or stop every motor
    @tether/<ns>/<role>/<id>             liveliness token of every process (hermetic: ``**`` never matches ``@``)

``<ns>`` is the run's namespace (the mission name by default). Every message is a msgspec Struct
in one tagged union, msgpack-encoded, carrying the wire version ``v``, the ``sender`` id, a
per-sender sequence number ``seq`` (from 0, +1 per message on that key) and the sample time
``t`` [s] of tick ``k``. A plain Zenoh client decodes any sample with::

    msgspec.msgpack.decode(payload, type=tether.wire.Message)

:class:`Receiver` decodes and checks a sample (version, tag, expected sender, vector sizes,
finiteness) and counts each reason for dropping it; it never raises.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

import msgspec

from tether.netprofile import LinkRule
from tether.schema import Strict

WIRE_VERSION = 1

TOKEN_ROOT = "@tether"
"""First chunk of every liveliness token; starting with ``@`` makes it hermetic (``*`` and ``**``
never match it, so only a subscriber that names ``@tether`` sees tokens)."""

Role = Literal["leader", "agent", "plant", "clock", "control", "recorder", "launcher", "world"]


class _Msg(Strict, tag_field="type", frozen=True, kw_only=True):
    v: int = WIRE_VERSION
    """Wire version."""
    sender: int
    """Id of the sending node (agent, plant or leader id; 0 for the clock and control)."""
    seq: int
    """Per-sender, per-key sequence number."""
    k: int
    """Tick index."""
    t: float
    """Sample time t_k = k h [s]."""


class State(_Msg, tag="state", frozen=True):
    """A node's state as its neighbours use it."""

    p: list[float]
    """Position [m; world frame]."""
    vel: list[float]
    """Velocity [m/s; world frame]."""
    a: list[float]
    """Acceleration [m/s^2; world frame]: the leader's reference, or a vehicle's measured mean
    acceleration over the previous period."""
    mode: int = 0
    """The sender's safety mode (a code of :data:`MODES`; the leader's is always FLYING): a
    neighbour that holds, lands or has stopped is no longer one to follow."""


class PlantState(_Msg, tag="plant_state", frozen=True):
    """A plant's measurement at t_k, and the disturbance it applied (for records, not for agents)."""

    p: list[float]
    vel: list[float]
    a: list[float]
    d: list[float]
    """True disturbance d(t_k) [m/s^2]; NaN where the plant cannot know it (a real vehicle)."""
    mode: int = 0
    """The plant's command watchdog: 0 (FLYING) while it follows its agent, else HOLD, LAND, LANDED
    or ESTOP (codes of :data:`MODES`)."""
    events: list["SafetyEvent"] = []
    """What the plant's watchdog noticed since its previous sample: its mode changes and the commands
    it rejected, clamped or flew outside the law's usual range (``src == dst`` when the mode did not
    change), for the log and the run file."""


class Command(_Msg, tag="cmd", frozen=True):
    u: list[float]
    """Commanded acceleration u_i(t_k) [m/s^2; world frame], held until the next command."""
    mode: int = 0
    """The agent's safety mode (a code of :data:`MODES`): a plant rests on LANDED and cuts its
    motors on ESTOP, whatever ``u`` says."""


class LinkStats(Strict, frozen=True, kw_only=True):
    """What agent i saw of one in-neighbour j up to tick k."""

    src: int
    received: int
    """Samples accepted from j."""
    used: int
    """Ticks at which a sample of j was used."""
    stale: int
    """Samples dropped for being older than the newest held (reordered or duplicated)."""
    age: float
    """Age of j's sample at the moment of use at this tick: t_k - t_sample [s] (NaN if none)."""
    silent: bool
    """j's liveliness token is gone."""
    duplicates: int = 0
    """Samples received twice (part of ``stale``)."""
    reordered: int = 0
    """Samples that arrived after a newer one (the rest of ``stale``)."""
    corrupt: int = 0
    """Copies that failed the checksum (decode failures), dropped."""
    delivery: float = 1.0
    """Distinct samples received over samples j sent up to its newest received (1: none lost)."""
    age_p50: float = 0.0
    """Median age of the samples used over the last ``agent.node.AGE_WINDOW`` ticks [s] (NaN: none used)."""
    age_p99: float = 0.0
    """99th percentile of the same [s]."""


class LinkDecision(Strict, frozen=True, kw_only=True):
    """What the emulated link ``src -> sender`` did with one copy (``[netem] log = true``)."""

    src: int
    seq: int
    """Index of the offer on that link, from 0."""
    now: float
    """When the sample entered the link [s; mission time]."""
    event: str
    """``deliver``, ``duplicate`` (``+reorder``, ``+corrupt``), or ``drop:loss|outage|queue``."""
    at: float | None
    """Delivery time [s]; None for a drop."""


MODES = ("FLYING", "HOLD", "LAND", "LANDED", "ESTOP")
"""Safety modes by integer code (telemetry, plant states and run files store the code). An agent's
supervisor is in one of them; a plant's command watchdog reports FLYING while it follows its
agent's commands, HOLD or LAND when it has taken over, LANDED, and ESTOP once its motors are off."""
FLYING, HOLD, LAND, LANDED, ESTOP = range(5)


class SafetyEvent(Strict, frozen=True, kw_only=True):
    """One mode change of a vehicle's supervisor or watchdog."""

    k: int
    """Tick of the change."""
    t: float
    """Its time [s; mission time]."""
    vehicle: int
    """The agent (= vehicle) id."""
    src: int
    """Mode before (a code of :data:`MODES`)."""
    dst: int
    """Mode after."""
    reason: str
    """Why, in a few words (``leader silent 0.52 s``, ``operator land``, ``geofence``, ...)."""


class ClockLink(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One input link's clock-offset bound (:mod:`tether.skew`): the low order statistic of
    arrival time minus sample time, = minimum delay + how far the receiver's clock is ahead."""

    role: str
    """The sender's role (``plant``, ``agent``, ``leader``)."""
    src: int
    offset: float
    """[s]; negative: the sender's clock is ahead by at least ``-offset``."""
    warn: bool = False
    """``offset`` is below minus half a control period or above one period (:func:`tether.skew.bounds`)."""


class Telemetry(_Msg, tag="telemetry", frozen=True):
    """Agent i's tick: what it measured, computed and saw."""

    meas_t: float
    """Sample time of the own measurement used at this tick [s] (t_k in lockstep; in real time
    the newest plant sample held, usually t_k when the agent ticks half a period after its plant)."""
    p: list[float]
    vel: list[float]
    a: list[float]
    u: list[float]
    xi: list[float]
    zeta: list[float]
    kp: list[float]
    kv: list[float]
    """The law's first two state variables (zeros where it has fewer), ``d`` floats each."""
    links: list[LinkStats]
    drops: dict[str, int]
    """Messages dropped since start, by reason (see :class:`Receiver`)."""
    late: int = 0
    """Real time: ticks that started more than one period late."""
    netem: list[LinkDecision] = []
    mode: int = FLYING
    """The safety supervisor's mode at this tick (a code of :data:`MODES`)."""
    events: list[SafetyEvent] = []
    """Mode changes since the previous telemetry message."""
    gate: dict[str, int] = {}
    """Samples the plausibility gate rejected since start, by reason (``future``, ``jump``, ...)."""
    """The emulated links' decisions since the previous tick (only with ``[netem] log = true``)."""
    clock: list[ClockLink] = []
    """Real time: each input link's clock-offset bound that has an estimate (:mod:`tether.skew`);
    absent from older senders' messages."""
    x: list[float] = []
    """The law's state at t_k, every variable of ``FormationLaw.state`` in its order, ``d`` floats
    each (variable-major: ``x[s * d + c]``); at most :data:`MAX_STATE` variables. Empty: the sender
    does not say it."""
    x_names: list[str] = []
    """The names of ``x``'s variables (``FormationLaw.state``), one per ``d`` floats, so that a
    listener without the mission (``tether top``) shows them by name; empty: not said."""


class Tick(_Msg, tag="tick", frozen=True):
    """Lockstep: every process may run ticks up to and including ``grant``."""

    grant: int


class Ack(_Msg, tag="ack", frozen=True):
    """Lockstep: the sender has finished every tick up to and including k (one acknowledgement
    stands for the ticks before it: the recorder sends one for the ticks it completes together)."""

    role: str


class Recorded(_Msg, tag="recorded", frozen=True):
    """Lockstep: the recorder holds every process's output of every tick up to and including k (the
    launcher's word, once the recorder has acknowledged the last tick): a producer that ran its last
    tick may close its session now without losing a sample on the way."""


class Start(_Msg, tag="start", frozen=True):
    """Real time: tick 0 is at ``epoch`` [s since the Unix epoch, UTC]; tick k at epoch + k h."""

    epoch: float


class WorldState(_Msg, tag="world_state", frozen=True):
    """A payload world's own state at t_k (for records; agents never use it)."""

    p: list[float]
    """Payload position [m]."""
    vel: list[float]
    """Payload velocity [m/s]."""
    tension: list[float]
    """Cable tension per vehicle, in the mission's agent order [N]."""
    slack_events: list[int]
    """Taut -> slack transitions per cable since the start."""


class SafetyCommand(_Msg, tag="safety", frozen=True):
    """Operator: ``land`` every vehicle (descend and disarm), or ``estop`` (motors off at once).
    Published on ``tether/<ns>/control/0/safety`` by ``tether land`` / ``tether estop``; only the
    operator identity may publish there under the generated access rules."""

    action: Literal["land", "estop"]
    reason: str = ""


class NetemSet(_Msg, tag="netem_set", frozen=True):
    """Control: change emulated links during a run (``tether netem-set``). Each rule, as in the
    mission's ``[netem] rules``, applies to the links it matches from ``at`` on; its ``start`` is
    ignored (``at`` says when)."""

    rules: list[LinkRule]
    at: float | None = None
    """When the change takes effect [s; mission time]; None: as soon as it is received. A time
    already past when it arrives takes effect at once (the receiving agent logs how late)."""


class Record(_Msg, tag="record", frozen=True):
    """Lockstep, plants co-located in their agents (``tether run --colocate-plants``): what the
    recorder would otherwise hear sample by sample, for consecutive ticks ending at ``k``, in one
    message (``--record-batch`` ticks at most). An agent's (on ``agent/<id>/record``) carries its
    plant's states and its telemetry, one of each per tick; the leader's (on ``leader/<id>/record``)
    its states alone, which it also puts tick by tick for its out-neighbours. Every item is checked
    as if it had come alone (sender, vector sizes, finiteness); one bad item drops the whole record."""

    plant: list[PlantState] = msgspec.field(default_factory=list)
    telemetry: list[Telemetry] = msgspec.field(default_factory=list)
    leader: list[State] = msgspec.field(default_factory=list)


Message = (State | PlantState | Command | Telemetry | Tick | Ack | Start | NetemSet | WorldState | SafetyCommand
           | Record | Recorded)
M = TypeVar("M", bound=Message)

_ENCODER = msgspec.msgpack.Encoder()
_DECODER = msgspec.msgpack.Decoder(Message)


class _Version(msgspec.Struct):
    """Only the wire version, read before the strict decode (unknown fields ignored), so that a
    message of another version is told apart from a malformed one."""

    v: int


_VERSION = msgspec.msgpack.Decoder(_Version)


def encode(msg: Message) -> bytes:
    return _ENCODER.encode(msg)


def decode(payload: bytes) -> Message:
    """Decode one message; raises ``msgspec.DecodeError``/``ValidationError`` on bad input."""
    return _DECODER.decode(payload)


# --------------------------------------------------------------------------- keys
@dataclass(frozen=True)
class Keys:
    """Key expressions of one run namespace."""

    ns: str

    def __post_init__(self) -> None:
        bad = set("/*$#?@ ") & set(self.ns)
        if not self.ns or bad:
            raise ValueError(f"namespace {self.ns!r} must be a non-empty key chunk without {sorted(bad) or '/*$#?@'}; "
                             "rename the mission or pass --ns")

    def topic(self, role: str, node: int, topic: str) -> str:
        return f"tether/{self.ns}/{role}/{node}/{topic}"

    def token(self, role: str, node: int | str) -> str:
        return f"{TOKEN_ROOT}/{self.ns}/{role}/{node}"

    @property
    def tokens(self) -> str:
        return f"{TOKEN_ROOT}/{self.ns}/**"

    @property
    def everything(self) -> str:
        return f"tether/{self.ns}/**"

    @property
    def tick(self) -> str:
        return self.topic("clock", 0, "tick")

    @property
    def acks(self) -> str:
        return f"tether/{self.ns}/*/*/ack"

    @property
    def start(self) -> str:
        return self.topic("control", 0, "start")

    @property
    def netem(self) -> str:
        return self.topic("control", 0, "netem")

    @property
    def recorded(self) -> str:
        return self.topic("control", 0, "recorded")

    @property
    def safety(self) -> str:
        return self.topic("control", 0, "safety")

    @staticmethod
    def parse(key: str) -> tuple[str, int, str]:
        """``tether/<ns>/<role>/<id>/<topic>`` -> ``(role, id, topic)``; raises ValueError."""
        parts = str(key).split("/")
        if len(parts) != 5 or parts[0] != "tether":
            raise ValueError(f"not a tether key: {key}")
        return parts[2], int(parts[3]), parts[4]

    @staticmethod
    def parse_token(key: str) -> tuple[str, int]:
        parts = str(key).split("/")
        if len(parts) != 4 or parts[0] != TOKEN_ROOT:
            raise ValueError(f"not a tether liveliness key: {key}")
        return parts[2], int(parts[3])


# --------------------------------------------------------------------------- checked receive
MAX_STATE = 4
"""The most per-axis state variables a law may have (:data:`agent.laws.MAX_STATE`): a
:class:`Telemetry`'s ``x`` holds at most this many times ``d`` floats."""
MAX_NAME = 32
"""The longest name of a law's state variable a :class:`Telemetry` may carry (characters)."""
RECORD_MAX = 256
"""The most ticks one :class:`Record` may carry (a larger one is dropped as ``size``)."""
_VECTOR_FIELDS = {State: ("p", "vel", "a"), PlantState: ("p", "vel", "a"), Command: ("u",),
                  Telemetry: ("p", "vel", "a", "u", "xi", "zeta", "kp", "kv"), WorldState: ("p", "vel")}


@dataclass
class Receiver:
    """Decodes and checks incoming samples; counts every drop by reason. Never raises.

    Reasons: ``malformed`` (not msgpack or not a known message), ``version`` (another wire
    version), ``type`` (a message of the wrong type for the key), ``sender`` (sender id differs
    from the key's), ``size`` (a vector of the wrong dimension), ``nonfinite`` (NaN/Inf where a
    number must be finite), ``record`` (a :class:`Record` whose items are not one of each stream
    per tick for consecutive ticks ending at its ``k``). Counted by others through :meth:`count`:
    ``overflow``, ``corrupt``. A :class:`Telemetry`'s law state ``x`` must be a whole number of
    vectors, at most :data:`MAX_STATE`, and finite, with a name (an identifier of at most
    :data:`MAX_NAME` characters) per vector where it names them (its count against the mission's law is the
    recorder's to check: the receiver does not know the law). (A lockstep copy sent again after a
    stall is no drop of these: :attr:`tether.node.Node.copies`.)
    """

    dim: int
    drops: dict[str, int] = field(default_factory=dict)

    def count(self, reason: str, n: int = 1) -> None:
        """Count ``n`` samples dropped for ``reason`` (also for drops decided outside :meth:`accept`:
        a queue's overflow, an emulated link's corrupt copy)."""
        self.drops[reason] = self.drops.get(reason, 0) + n

    def _drop(self, reason: str) -> None:
        self.count(reason)

    def accept(self, payload: bytes, expect: type[M], sender: int | None) -> M | None:
        try:
            msg = _DECODER.decode(payload)
        except (msgspec.DecodeError, msgspec.ValidationError, RecursionError):
            # only now read the version: a message of another version is not a malformed one (a
            # payload nested thousands deep makes msgspec raise RecursionError: malformed too)
            try:
                other = _VERSION.decode(payload).v != WIRE_VERSION
            except (msgspec.DecodeError, msgspec.ValidationError, RecursionError):
                other = False
            self._drop("version" if other else "malformed")
            return None
        if msg.v != WIRE_VERSION:
            self._drop("version")
            return None
        if not isinstance(msg, expect):
            self._drop("type")
            return None
        if sender is not None and msg.sender != sender:
            self._drop("sender")
            return None
        if isinstance(msg, Record):
            # the leader's carries its states alone; an agent's its plant's states and its telemetry,
            # one of each per tick
            streams: list[list[Any]] = [msg.leader] if msg.leader else [msg.plant, msg.telemetry]
            n = len(streams[0])
            if (msg.leader and (msg.plant or msg.telemetry)) or not n or n > RECORD_MAX \
                    or any(len(stream) != n for stream in streams):
                self._drop("size")
                return None
            first = msg.k - n + 1
            if any(x.k != first + i for stream in streams for i, x in enumerate(stream)):
                self._drop("record")  # not one sample of each stream per tick, for consecutive ticks ending at k
                return None
            items: list[Message] = [x for stream in streams for x in stream]
            for item in items:
                if item.v != WIRE_VERSION:
                    self._drop("version")
                    return None
                if item.sender != msg.sender:
                    self._drop("sender")
                    return None
                why = self._check(item)
                if why is not None:
                    self._drop(why)
                    return None
            return msg
        why = self._check(msg)
        if why is not None:
            self._drop(why)
            return None
        return msg

    def _check(self, msg: Message) -> str | None:
        """Why ``msg``'s numbers cannot be used (``nonfinite``, ``size``), or None."""
        if not math.isfinite(msg.t) or (isinstance(msg, Start) and not math.isfinite(msg.epoch)) \
                or (isinstance(msg, Telemetry) and not (math.isfinite(msg.meas_t)
                                                         and all(math.isfinite(c.offset) for c in msg.clock))):
            return "nonfinite"
        for name in _VECTOR_FIELDS.get(type(msg), ()):
            vec = getattr(msg, name)
            if len(vec) != self.dim:
                return "size"
            if not all(map(math.isfinite, vec)):
                return "nonfinite"
        if isinstance(msg, Telemetry):
            if len(msg.x) % self.dim or len(msg.x) > MAX_STATE * self.dim \
                    or (msg.x_names and len(msg.x_names) * self.dim != len(msg.x)):
                return "size"
            if not all(0 < len(name) <= MAX_NAME and name.isidentifier() for name in msg.x_names):
                return "malformed"
            if not all(map(math.isfinite, msg.x)):
                return "nonfinite"
        return None
