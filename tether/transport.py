"""The project's one place that touches Zenoh: settings, sessions, publishers, hand-off sinks, liveliness.

zenoh-python 1.x has no asyncio API. Every subscriber callback here runs on a thread that Zenoh owns
(a Python thread that zenoh-python starts per subscriber), so callbacks only *hand off*: they copy the
key and the payload bytes into a sink (:class:`LatestSlot` for state, :class:`BoundedFifo` for
commands and events) and, optionally, poke a :class:`Wakeup` so that the asyncio task sleeps until
there is work. Nothing in a callback calls Zenoh, decodes, logs, or blocks beyond a short lock.

Pieces, in the order a process uses them:

- :class:`ZenohSettings` → :func:`zenoh_config` (validated; a bad field raises :class:`SettingsError`
  naming it) → :func:`open_session` (``with`` or ``async with``; the session is always closed).
- :func:`declare_publisher` with a :class:`StreamQos` preset (:data:`STATE`, :data:`COMMAND`,
  :data:`TELEMETRY`, :data:`SYNC`), and :func:`declare_subscriber` into a sink.
- :func:`declare_token` on :func:`token_key`; :func:`watch_tokens` (with history) and
  :func:`wait_for_tokens` for launchers.

Measured behaviour, verified config keys and the latency figures are in ``docs/zenoh.md``.
"""

from __future__ import annotations

import asyncio
import errno
import math
import re
import socket
import threading
from collections.abc import Callable, Iterable, Mapping
from types import TracebackType
from typing import TYPE_CHECKING, Any, Literal, NamedTuple, TypeVar

import msgspec
import zenoh

from tether import wire
from tether.handoff import BoundedFifo, Sink, Wakeup
from tether.schema import Problems, SchemaError, Strict, read_issue

if TYPE_CHECKING:
    import random

__all__ = [
    "COMMAND",
    "STATE",
    "SYNC",
    "TELEMETRY",
    "Received",
    "SessionScope",
    "SettingsError",
    "StreamQos",
    "TlsFiles",
    "TokenEvent",
    "TokensMissing",
    "TransportError",
    "ZenohSettings",
    "declare_publisher",
    "declare_subscriber",
    "declare_token",
    "endpoint_port",
    "free_tcp_port",
    "listen_problem",
    "load_settings",
    "loopback_endpoint",
    "open_session",
    "reserve_ports",
    "token_key",
    "validate_settings",
    "wait_for_subscribers",
    "wait_for_tokens",
    "watch_tokens",
    "zenoh_config",
]

T = TypeVar("T")

TOKEN_ROOT = wire.TOKEN_ROOT


# =========================================================================== settings
class TlsFiles(Strict, frozen=True):
    """Paths of TLS material, carried into ``transport/link/tls/*``. Used only by ``tls/`` endpoints.

    The keys are those of zenoh 1.10's config; opened with real certificates (mTLS) in tests/test_deploy.py.
    """

    root_ca_certificate: str | None = None
    """CA certificate (PEM path) that verifies the other side."""
    listen_certificate: str | None = None
    """Certificate (PEM path) presented by this node's listeners."""
    listen_private_key: str | None = None
    """Private key (PEM path) of ``listen_certificate``."""
    connect_certificate: str | None = None
    """Certificate (PEM path) presented when connecting (mTLS)."""
    connect_private_key: str | None = None
    """Private key (PEM path) of ``connect_certificate``."""
    enable_mtls: bool = False
    """Require client certificates on listeners (mutual TLS)."""


class ZenohSettings(Strict, frozen=True):
    """How one process joins the Zenoh network. Immutable; turned into a ``zenoh.Config`` by :func:`zenoh_config`.

    The defaults isolate a process: multicast scouting is off and nothing is listened on or
    connected to unless named, so tests and runs on one machine never discover strangers.
    """

    mode: Literal["peer", "client", "router"] = "peer"
    """``peer`` (direct links, no relaying), ``client`` (one link to a router) or ``router`` (relays)."""
    listen: tuple[str, ...] = ()
    """Endpoints to listen on, ``<proto>/<host>:<port>`` (e.g. ``tcp/127.0.0.1:7447``). Empty: listen nowhere."""
    connect: tuple[str, ...] = ()
    """Endpoints to connect to at start-up (a client's router, a peer's seed)."""
    multicast_scouting: bool = False
    """UDP multicast discovery (``scouting/multicast/enabled``). Off: only named endpoints and gossip."""
    gossip: bool = True
    """Gossip discovery through already-connected nodes (``scouting/gossip/enabled``); peers use it to mesh."""
    peer_autoconnect: Literal["always", "greater-zid"] = "greater-zid"
    """Which side of a peer pair opens the link found by gossip/multicast. ``greater-zid`` opens one link
    per pair instead of two racing ones (the default ``always`` left subscriptions unmatched in a 65-process
    mesh here). Every peer must then listen on an endpoint the others can reach."""
    lease: float | None = None
    """Link lease [s] (``transport/link/tx/lease``): a frozen or partitioned node is declared gone after it.
    ``None`` keeps Zenoh's 10 s; 1-2 s suits liveliness in flight. A killed process is seen at once anyway."""
    keep_alive: int | None = None
    """Keep-alive messages per lease (``transport/link/tx/keep_alive``); ``None`` keeps Zenoh's 4."""
    scouting_delay: float | None = None
    """How long [s] opening waits for peers found by scouting (``scouting/delay``). ``None`` keeps Zenoh's
    0.5 s, which a router or a dialling peer may spend in full; 0 returns at once, and samples put before
    the other side is connected are lost (use :func:`wait_for_subscribers` where that matters)."""
    connect_timeout: float | None = None
    """How long [s] opening waits for ``connect`` endpoints, retrying (``connect/timeout_ms``). ``None`` keeps
    Zenoh's default, under which a client fails at once if its router is not up yet."""
    tls: TlsFiles | None = None
    """TLS files for ``tls/`` endpoints; ``None``: no TLS."""
    ingress_limits: tuple[tuple[str, float], ...] = ()
    """Per-link ingress rate limits, ``(key expression, messages per second)``: Zenoh's
    ``downsampling`` (``flows = ["ingress"]``, messages ``put`` and ``delete``), applied in Zenoh's
    own threads before any callback. Each link has its own budget per rule (a flooding session
    cannot use up another's), the most specific rule applies to a key, and within a rule a message
    arriving sooner than ``1/rate`` after the last one passed is dropped (a burst keeps its first)."""
    config_file: str | None = None
    """A complete Zenoh JSON5 configuration file (such as those ``tether deploy-gen`` writes, with TLS
    and access control), read with ``zenoh.Config.from_file``. It is then the whole configuration:
    every other field must keep its default."""


class SettingsError(SchemaError):
    """Settings are not valid. ``problems`` holds one ``(field, message)`` pair per problem; the
    source is always ``zenoh settings``."""

    def __init__(self, problems: Problems):
        super().__init__("zenoh settings", problems)


class TransportError(RuntimeError):
    """Zenoh refused to open a session (address in use, router unreachable, ...); the message says which."""


_HOST_PORT_PROTOCOLS = frozenset({"tcp", "udp", "tls", "quic", "ws"})
_OTHER_PROTOCOLS = frozenset({"unixsock-stream", "unixpipe", "vsock", "serial"})
_ENDPOINT = re.compile(r"^(?P<proto>[a-z][a-z0-9-]*)/(?P<addr>[^?#]+)(?:\?[^#]*)?(?:#.*)?$")
_HOST_PORT = re.compile(r"^(?P<host>\[[0-9A-Fa-f:.%a-z]+\]|[^:\[\]]+):(?P<port>[0-9]+)$")


def _endpoint_problem(endpoint: object, *, listening: bool) -> str | None:
    """What is wrong with one endpoint string, or ``None``. Zenoh itself accepts ports > 65535 and
    unknown protocols at config time and fails only when opening, so they are checked here."""
    if not isinstance(endpoint, str):
        return f"is {endpoint!r}; an endpoint is a string such as 'tcp/127.0.0.1:7447'"
    m = _ENDPOINT.match(endpoint)
    if m is None:
        return f"{endpoint!r} is not of the form <proto>/<address>, e.g. 'tcp/127.0.0.1:7447'"
    proto, addr = m["proto"], m["addr"]
    if proto not in _HOST_PORT_PROTOCOLS | _OTHER_PROTOCOLS:
        known = ", ".join(sorted(_HOST_PORT_PROTOCOLS | _OTHER_PROTOCOLS))
        return f"{endpoint!r} uses unknown protocol {proto!r}; use one of {known}"
    if proto in _HOST_PORT_PROTOCOLS:
        hp = _HOST_PORT.match(addr)
        if hp is None:
            return f"{endpoint!r} has no <host>:<port>; write e.g. '{proto}/127.0.0.1:7447'"
        port = int(hp["port"])
        lowest = 0 if listening else 1
        if not lowest <= port <= 65535:
            what = "0 (any free port) to 65535" if listening else "1 to 65535"
            return f"{endpoint!r} has port {port}; a port is {what}"
    return None


def listen_problem(endpoint: str) -> str | None:
    """Whether this machine can listen on ``endpoint`` now, checked before anything starts (Zenoh
    finds out only when the session opens): the syntax (:func:`validate_settings`), then for a
    ``<host>:<port>`` protocol that the host resolves to an address of this machine and that the
    port can be bound there (bound and released at once). ``None`` when it can; else one line
    naming the cause and the fix. Blocks for a name lookup."""
    problem = _endpoint_problem(endpoint, listening=True)
    if problem is not None:
        return problem
    m = _ENDPOINT.match(endpoint)
    assert m is not None
    proto, addr = m["proto"], m["addr"]
    hp = _HOST_PORT.match(addr)
    if proto not in _HOST_PORT_PROTOCOLS or hp is None:
        return None
    host, port = hp["host"].strip("[]"), int(hp["port"])
    kind = socket.SOCK_DGRAM if proto in ("udp", "quic") else socket.SOCK_STREAM
    example = f"{proto}/127.0.0.1:{port} or {proto}/0.0.0.0:{port}"
    try:
        infos = socket.getaddrinfo(host, port, type=kind)
    except (socket.gaierror, UnicodeError) as exc:
        return f"cannot resolve {host!r} ({exc}); give an address of this machine, e.g. {example}"
    family, socktype, sproto, _, sockaddr = infos[0]
    with socket.socket(family, socktype, sproto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(sockaddr)
        except OSError as exc:
            why = ("the port is in use" if exc.errno == errno.EADDRINUSE else
                   f"{host} is not an address of this machine" if exc.errno == errno.EADDRNOTAVAIL else
                   exc.strerror or str(exc))
            return f"cannot listen on {sockaddr[0]}:{port}: {why}; give a free port on an address of this machine, " \
                   f"e.g. {example}"
    return None


def _positive_seconds(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0


def validate_settings(s: ZenohSettings) -> Problems:
    """Every problem of ``s``, as ``(field, message-with-fix)`` pairs; empty when valid.

    Checks what Zenoh checks late or not at all: mode, endpoint syntax and ports, that a client has
    somewhere to connect, that a router names its listeners, and positive lease and keep-alive
    (Zenoh silently turns a negative lease into 0 and truncates it to whole milliseconds).
    """
    out: Problems = []
    if s.config_file is not None:
        return _config_file_problems(s)
    if s.mode not in ("peer", "client", "router"):
        out.append(("mode", f"is {s.mode!r}; use 'peer', 'client' or 'router'"))
    for name, endpoints, listening in (("listen", s.listen, True), ("connect", s.connect, False)):
        if isinstance(endpoints, (str, bytes)) or not isinstance(endpoints, (tuple, list)):
            out.append((name, f"is {endpoints!r}; give a list of endpoints, e.g. ['tcp/127.0.0.1:7447']"))
            continue
        for i, ep in enumerate(endpoints):
            problem = _endpoint_problem(ep, listening=listening)
            if problem is not None:
                out.append((f"{name}[{i}]", problem))
        if len(set(endpoints)) != len(endpoints):
            out.append((name, "names an endpoint twice; remove the duplicate"))
    for name in ("multicast_scouting", "gossip"):
        if not isinstance(getattr(s, name), bool):
            out.append((name, f"is {getattr(s, name)!r}; use true or false"))
    if s.peer_autoconnect not in ("always", "greater-zid"):
        out.append(("peer_autoconnect", f"is {s.peer_autoconnect!r}; use 'always' or 'greater-zid'"))
    if s.mode == "client":
        if not s.connect and s.multicast_scouting is not True:
            out.append(("connect", "is empty; a client needs its router's endpoint (or multicast_scouting on)"))
        if s.listen:
            out.append(("listen", "is set for a client; clients do not accept links: remove it or use mode 'peer'"))
    if s.mode == "router" and not s.listen:
        out.append(("listen", "is empty; a router must listen, e.g. ['tcp/127.0.0.1:7447']"))
    if s.mode == "peer" and not s.listen and not s.connect and s.multicast_scouting is not True:
        out.append(("listen", "and connect are both empty with multicast scouting off: this peer can reach "
                              "nobody; listen on e.g. 'tcp/127.0.0.1:0' or connect to a seed"))
    if s.lease is not None:
        if not _positive_seconds(s.lease):
            out.append(("lease", f"is {s.lease!r}; the lease is a duration in seconds > 0 (1-2 s is typical)"))
        elif s.lease < 0.001:
            out.append(("lease", f"is {s.lease} s; Zenoh counts the lease in whole milliseconds: use >= 0.001"))
    if s.keep_alive is not None and (
        not isinstance(s.keep_alive, int) or isinstance(s.keep_alive, bool) or s.keep_alive < 1
    ):
        out.append(("keep_alive", f"is {s.keep_alive!r}; it counts keep-alives per lease: an integer >= 1 (e.g. 4)"))
    if s.scouting_delay is not None and not (_positive_seconds(s.scouting_delay) or s.scouting_delay == 0):
        out.append(("scouting_delay", f"is {s.scouting_delay!r}; give seconds >= 0, or leave it unset"))
    if s.connect_timeout is not None and not _positive_seconds(s.connect_timeout):
        out.append(("connect_timeout", f"is {s.connect_timeout!r}; give seconds > 0, or leave it unset"))
    for i, limit in enumerate(s.ingress_limits):
        if not (isinstance(limit, (tuple, list)) and len(limit) == 2 and isinstance(limit[0], str)
                and _positive_seconds(limit[1])):
            out.append((f"ingress_limits[{i}]", f"is {limit!r}; give (key expression, messages per second > 0)"))
    if s.tls is not None:
        for side in ("listen", "connect"):
            cert, key = getattr(s.tls, f"{side}_certificate"), getattr(s.tls, f"{side}_private_key")
            if (cert is None) != (key is None):
                out.append((f"tls.{side}_certificate", f"and tls.{side}_private_key go together; give both or neither"))
    return out


def _config_file_problems(s: ZenohSettings) -> Problems:
    """With ``config_file`` the file is the whole configuration: any other field set is a conflict."""
    if not isinstance(s.config_file, str) or not s.config_file:
        return [("config_file", f"is {s.config_file!r}; give the path of a Zenoh JSON5 file")]
    defaults = ZenohSettings()
    mixed = [f.name for f in msgspec.structs.fields(ZenohSettings)
             if f.name != "config_file" and getattr(s, f.name) != getattr(defaults, f.name)]
    if mixed:
        return [("config_file", f"is given together with {', '.join(mixed)}; the file is the whole "
                                "configuration: put those settings in the file, or drop config_file")]
    return []


def load_settings(raw: Mapping[str, Any]) -> ZenohSettings:
    """Settings from a mapping (a TOML table, say). Unknown or mistyped fields and invalid values raise
    :class:`SettingsError` naming the field."""
    try:
        s = msgspec.convert(raw, ZenohSettings)
    except msgspec.ValidationError as exc:
        issue = read_issue(exc)
        raise SettingsError([(issue.field or "<settings>", issue.text)]) from None
    problems = validate_settings(s)
    if problems:
        raise SettingsError(problems)
    return s


def _json(value: object) -> str:
    return msgspec.json.encode(value).decode()


def zenoh_config(settings: ZenohSettings) -> zenoh.Config:
    """Build the ``zenoh.Config`` for ``settings`` with ``insert_json5``. Raises :class:`SettingsError`.

    Keys written (zenoh 1.10): ``mode``, ``listen/endpoints``, ``connect/endpoints``,
    ``scouting/multicast/enabled``, ``scouting/gossip/enabled``,
    ``scouting/gossip/autoconnect_strategy`` (and the multicast one), ``transport/link/tx/lease`` [ms],
    ``transport/link/tx/keep_alive``, ``transport/link/tx/queue/size`` (a router: :data:`ROUTER_TX_QUEUE`),
    ``scouting/delay`` [ms], ``connect/timeout_ms``, ``transport/link/tls/*``.
    With ``config_file``, the configuration is that file as Zenoh reads it, and nothing is added.
    Does not block and opens nothing (reads the file).
    """
    problems = validate_settings(settings)
    if problems:
        raise SettingsError(problems)
    if settings.config_file is not None:
        try:
            return zenoh.Config.from_file(settings.config_file)
        except (zenoh.ZError, OSError) as exc:
            raise SettingsError([("config_file", f"{settings.config_file!r} is not a Zenoh configuration "
                                                 f"Zenoh can read: {exc}")]) from None
    strategy = {"peer": {"to_router": "always", "to_peer": settings.peer_autoconnect}}
    entries: list[tuple[str, str, object]] = [
        ("mode", "mode", settings.mode),
        ("listen", "listen/endpoints", list(settings.listen)),
        ("connect", "connect/endpoints", list(settings.connect)),
        ("multicast_scouting", "scouting/multicast/enabled", settings.multicast_scouting),
        ("gossip", "scouting/gossip/enabled", settings.gossip),
        ("peer_autoconnect", "scouting/gossip/autoconnect_strategy", strategy),
        ("peer_autoconnect", "scouting/multicast/autoconnect_strategy", strategy),
    ]
    if settings.lease is not None:
        entries.append(("lease", "transport/link/tx/lease", max(1, round(settings.lease * 1000))))
    if settings.keep_alive is not None:
        entries.append(("keep_alive", "transport/link/tx/keep_alive", settings.keep_alive))
    if settings.scouting_delay is not None:
        entries.append(("scouting_delay", "scouting/delay", round(settings.scouting_delay * 1000)))
    if settings.connect_timeout is not None:
        entries.append(("connect_timeout", "connect/timeout_ms", max(1, round(settings.connect_timeout * 1000))))
    if settings.mode == "router":
        entries.append(("mode", "transport/link/tx/queue/size", ROUTER_TX_QUEUE))
    if settings.ingress_limits:
        entries.append(("ingress_limits", "downsampling", downsampling(settings.ingress_limits)))
    if settings.tls is not None:
        for name in msgspec.structs.fields(TlsFiles):
            value = getattr(settings.tls, name.name)
            if value is not None:
                entries.append((f"tls.{name.name}", f"transport/link/tls/{name.name}", value))
    config = zenoh.Config()
    for field, key, value in entries:
        try:
            config.insert_json5(key, _json(value))
        except zenoh.ZError as exc:
            raise SettingsError([(field, f"rejected by Zenoh at {key!r}: {exc}")]) from None
    return config


def downsampling(limits: Iterable[tuple[str, float]]) -> list[dict[str, Any]]:
    """Zenoh's ``downsampling`` section for :attr:`ZenohSettings.ingress_limits`."""
    return [{"id": "tether-ingress", "messages": ["put", "delete"], "flows": ["ingress"],
             "rules": [{"key_expr": k, "freq": float(f)} for k, f in limits]}]


# =========================================================================== endpoints
def loopback_endpoint(port: int) -> str:
    """The TCP endpoint ``tcp/127.0.0.1:<port>``."""
    return f"tcp/127.0.0.1:{port}"


def _ephemeral_low() -> int:
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            return int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


_GIVEN: set[int] = set()
"""Ports :func:`free_tcp_port` has returned in this process: never returned again."""
_GIVEN_LOCK = threading.Lock()


def free_tcp_port(rng: random.Random | None = None, span: int = 1) -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now (with ``span`` > 1: the first of that
    many consecutive ones). Blocks for microseconds.

    Picked at random *below* the kernel's ephemeral range and checked by binding it, so the outgoing
    connections of other sockets (which take ephemeral ports) cannot grab it before the caller binds.
    A port is only free while nobody binds it, so two calls in a row could return the same one (a
    launcher giving two peers of a mesh one port; a deployment test once gave an agent the leader's):
    a port returned is never returned again by this process. A race with another process choosing
    the same port remains possible but unlikely; the caller should bind soon. ``rng`` is for
    reproducible tests; by default a fresh OS-seeded generator.
    """
    if rng is None:
        import random  # here: only a launcher picks ports, and every process loads this module

        rng = random.Random()
    high = _ephemeral_low() - span
    low = max(1024, min(10000, high - 1000))
    for _ in range(200):
        port = rng.randint(low, high)
        if _free_now(range(port, port + span)) and _give(range(port, port + span)):
            return port
    for _ in range(200 if span == 1 else 0):  # crowded machine: let the kernel choose (a single port)
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        if _give(range(port, port + 1)):
            return port
    raise OSError(f"no {span} free TCP port(s) on 127.0.0.1 that this process has not given out already")


def endpoint_port(endpoint: str) -> int | None:
    """The port of a ``<proto>/<host>:<port>`` endpoint; ``None`` for other protocols or bad syntax."""
    m = _ENDPOINT.match(endpoint)
    hp = _HOST_PORT.match(m["addr"]) if m is not None and m["proto"] in _HOST_PORT_PROTOCOLS else None
    return int(hp["port"]) if hp is not None else None


def reserve_ports(endpoints: Iterable[str]) -> None:
    """Never let :func:`free_tcp_port` return a port that one of ``endpoints`` names: a port the
    user gave (``--listen``) is free until its session binds it, so a launcher picking its own
    router's port in between could otherwise pick the same one."""
    with _GIVEN_LOCK:
        _GIVEN.update(p for p in map(endpoint_port, endpoints) if p)


def _free_now(ports: range) -> bool:
    for port in ports:
        if port in _GIVEN:
            return False
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                return False
    return True


def _give(ports: range) -> bool:
    """Mark ``ports`` given, unless one of them already is (another thread's pick)."""
    with _GIVEN_LOCK:
        if any(p in _GIVEN for p in ports):
            return False
        _GIVEN.update(ports)
        return True


# =========================================================================== sessions
class SessionScope:
    """Owns one Zenoh session: opens it on entry, always closes it on exit.

    ``with open_session(s) as session:`` opens in the calling thread (blocks up to the connect
    timeout; milliseconds on loopback). ``async with open_session(s) as session:`` opens and closes
    in a worker thread so the event loop keeps running. Closing undeclares everything the session
    declared; an unclosed session can hang the interpreter at exit, hence this scope.
    """

    def __init__(self, settings: ZenohSettings):
        self._config = zenoh_config(settings)  # validate now, before anything is opened
        self._settings = settings
        self._session: zenoh.Session | None = None

    def _open(self) -> zenoh.Session:
        if self._session is not None:
            raise RuntimeError("this SessionScope is already open; make one scope per session")
        try:
            self._session = zenoh.open(self._config)
        except zenoh.ZError as exc:
            s = self._settings
            where = (f"config_file={s.config_file}" if s.config_file is not None
                     else f"mode={s.mode}, listen={list(s.listen)}, connect={list(s.connect)}")
            raise TransportError(f"cannot open a zenoh session ({where}): {exc}") from None
        return self._session

    def _close(self) -> None:
        session, self._session = self._session, None
        if session is not None:
            session.close()

    def __enter__(self) -> zenoh.Session:
        return self._open()

    def __exit__(self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None) -> None:
        self._close()

    async def __aenter__(self) -> zenoh.Session:
        return await asyncio.to_thread(self._open)

    async def __aexit__(self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None) -> None:
        await asyncio.shield(asyncio.to_thread(self._close))


def open_session(settings: ZenohSettings) -> SessionScope:
    """A scope that opens a session for ``settings`` and always closes it (``with`` or ``async with``).

    Raises :class:`SettingsError` at once for invalid settings, :class:`TransportError` on entry if
    Zenoh cannot open (address in use, router unreachable within ``connect_timeout``, ...).
    """
    return SessionScope(settings)


# =========================================================================== publish / subscribe
class StreamQos(NamedTuple):
    """Quality of service of one kind of stream, applied when its publisher is declared."""

    priority: zenoh.Priority
    """Zenoh priority; each priority has its own transmission queue, so streams do not queue behind each other."""
    congestion_control: zenoh.CongestionControl
    """DROP: a full queue drops the sample (after ~1 ms) instead of stalling the publisher."""
    express: bool
    """Send at once, without waiting to batch with later messages."""


ROUTER_TX_QUEUE = {"control": 2, "real_time": 16, "interactive_high": 16, "interactive_low": 2, "data_high": 2,
                   "data": 2, "data_low": 16, "background": 2}
"""A router's transmission queue per link, in batches per priority (``transport/link/tx/queue/size``):
16 on the three priorities the streams use, Zenoh's 2 elsewhere. Express samples
(states, commands) take a batch each, so with Zenoh's 2 the router's link to a process that hears
many streams (the recorder hears every plant, which all publish at the same phase) overflowed
whenever the burst of one tick outran its transmission thread by a moment: after ~1 ms (DROP's
``wait_before_drop``) the sample was dropped. Measured, a ring of 8 at 50 Hz on an idle machine:
55-71 of 12 767 samples lost with 2, 0-19 with 16 (four runs, with and without TLS; what is left is
the odd tick whose every plant sample was lost at once, a stall); the control loops never saw the
losses (each agent hears only its own plant). The queues are allocated lazily: memory is spent only by a
link that has queued that much."""

COMMAND = StreamQos(zenoh.Priority.REAL_TIME, zenoh.CongestionControl.DROP, express=True)
"""Agent → plant commands: highest data priority; a stale command is worth less than the next one."""
STATE = StreamQos(zenoh.Priority.INTERACTIVE_HIGH, zenoh.CongestionControl.DROP, express=True)
"""Measured and shared states (p, v, a), the leader state: the newest sample supersedes the last."""
FLEET_STATE = StreamQos(zenoh.Priority.INTERACTIVE_HIGH, zenoh.CongestionControl.DROP, express=False)
"""A world's vehicles' states (``--shared-plants``): one session sends every vehicle's sample at the
same instant, so they are batched together and take one batch of its transmission queue, where
express samples take one each (Zenoh's 2 on a client session): measured, a world of 8 vehicles
publishing express lost the last 3–4 samples of a tick's burst twice in a 10 s run at 50 Hz."""
SYNC = StreamQos(zenoh.Priority.INTERACTIVE_LOW, zenoh.CongestionControl.BLOCK, express=True)
"""Lockstep clock ticks and acknowledgements, which must not be dropped. BLOCK can stall the publisher
behind a slow reader (Zenoh closes the link after 5 s); in lockstep the whole run waits for that reader anyway."""
TELEMETRY = StreamQos(zenoh.Priority.DATA_LOW, zenoh.CongestionControl.DROP, express=False)
"""Per-tick telemetry (ξ, ζ, gains, u) for the recorder: lowest priority, batched, droppable."""


def declare_publisher(session: zenoh.Session, key_expr: str, qos: StreamQos = STATE) -> zenoh.Publisher:
    """A publisher on ``key_expr`` with ``qos`` (default :data:`STATE`). ``put`` on it returns
    immediately for DROP streams. Undeclare it, use it as a context manager, or let the session close it."""
    return session.declare_publisher(
        key_expr,
        congestion_control=qos.congestion_control,
        priority=qos.priority,
        express=qos.express,
    )


class Received(NamedTuple):
    """One sample as handed off by a subscriber callback: still undecoded."""

    key: str
    """The concrete key it was published on."""
    payload: bytes
    """The payload bytes (decode them on the asyncio side)."""
    at: float = math.nan
    """When the callback got it [s, on the stamping clock] (NaN: not stamped)."""


class _Tick(msgspec.Struct):
    """Only a message's tick, read without the strict decode (unknown fields ignored)."""

    k: int


_TICK = msgspec.msgpack.Decoder(_Tick)


def tick_of(rec: Received) -> int | None:
    """The tick a sample's payload says it is of, or None (not a message with one, malformed).
    Cheap (a microsecond: one pass over the bytes, nothing kept but ``k``) and never raises: an
    :class:`~tether.handoff.InputQueue` asks it on Zenoh's thread."""
    try:
        return _TICK.decode(rec.payload).k
    except (msgspec.DecodeError, TypeError, ValueError):
        return None


def declare_subscriber(session: zenoh.Session, key_expr: str, sink: Sink[Received],
                       stamp: Callable[[], float] | None = None) -> zenoh.Subscriber[None]:
    """Subscribe to ``key_expr``; every sample is handed to ``sink.put`` as a :class:`Received`.

    The callback runs on a Python thread that zenoh-python starts for this subscriber (fed by a
    Zenoh channel of 256 samples, which blocks Zenoh's receive path only if that thread starves).
    It copies key and payload and calls ``sink.put`` — nothing else. DELETE samples are handed off
    too (with an empty payload) and fail decoding like any malformed message. ``stamp``: a clock
    (``time.monotonic``) read in the callback, into :attr:`Received.at`, for a sink that is drained
    later than samples arrive.
    """
    if stamp is not None:
        def on_stamped(sample: zenoh.Sample) -> None:
            sink.put(Received(str(sample.key_expr), sample.payload.to_bytes(), stamp()))

        return session.declare_subscriber(key_expr, on_stamped)

    def on_sample(sample: zenoh.Sample) -> None:
        sink.put(Received(str(sample.key_expr), sample.payload.to_bytes()))

    return session.declare_subscriber(key_expr, on_sample)


def has_subscribers(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber matches ``publisher`` now (does not block)."""
    # zenoh-python 1.10's stub types ``matching_status`` as bool; at run time it is a MatchingStatus
    return bool(publisher.matching_status.matching)  # type: ignore[attr-defined]


async def wait_for_subscribers(publisher: zenoh.Publisher, timeout: float) -> None:
    """Return once at least one subscriber matches ``publisher``; ``TimeoutError`` after ``timeout`` [s].

    Samples put before a match are silently not delivered (no one is known to want them); start a
    stream after this returns when its first samples matter. Note: ``Publisher.matching_status`` is a
    ``MatchingStatus`` object (always truthy) in zenoh-python 1.10, despite its stub saying ``bool``.
    """
    wakeup = Wakeup()
    listener = publisher.declare_matching_listener(lambda _status: wakeup.notify())
    try:
        async with asyncio.timeout(timeout):
            while not has_subscribers(publisher):
                await wakeup.wait()
    except TimeoutError:
        raise TimeoutError(f"no subscriber matched {publisher.key_expr} within {timeout} s") from None
    finally:
        listener.undeclare()


# =========================================================================== liveliness
def token_key(mission: str, role: str, ident: int | str) -> str:
    """The liveliness key of one process: ``@tether/<mission>/<role>/<id>``."""
    for name, part in (("mission", mission), ("role", role), ("id", str(ident))):
        if not part or any(c in part for c in "/*$?#@ "):
            raise ValueError(
                f"{name} is {part!r}; a key chunk is non-empty, without '/', '*', '$', '?', '#', '@' or spaces"
            )
    return wire.Keys(mission).token(role, ident)


def declare_token(session: zenoh.Session, key: str) -> zenoh.LivelinessToken:
    """Declare this process alive under ``key`` until the token is undeclared, **garbage-collected**, or
    its session ends (a killed process is seen gone at once, a frozen one after the lease). Keep a
    reference or use it with ``with``: a token whose last reference is dropped is undeclared."""
    return session.liveliness().declare_token(key)


class TokenEvent(NamedTuple):
    """A liveliness change."""

    key: str
    """The token's key, e.g. ``@tether/m/agent/1``."""
    alive: bool
    """``True``: appeared (Zenoh ``SampleKind.PUT``); ``False``: gone (``SampleKind.DELETE``)."""


def watch_tokens(session: zenoh.Session, key_expr: str, sink: Sink[TokenEvent]) -> zenoh.Subscriber[None]:
    """Hand every appearance and disappearance of a token matching ``key_expr`` to ``sink.put``.

    Tokens present at declaration are reported first (history). ``key_expr`` must name the ``@tether``
    chunk explicitly (``@tether/m/**``): wildcards never match chunks that start with ``@``. Use a
    :class:`BoundedFifo` as sink so that no event is lost to overwriting.
    """
    put_kind = zenoh.SampleKind.PUT  # Zenoh's enums are not hashable: compare, do not look up

    def on_sample(sample: zenoh.Sample) -> None:
        sink.put(TokenEvent(str(sample.key_expr), sample.kind == put_kind))

    return session.liveliness().declare_subscriber(key_expr, on_sample, history=True)


class TokensMissing(TimeoutError):
    """Not every expected liveliness token appeared in time. ``missing`` lists the absent keys."""

    def __init__(self, missing: list[str], timeout: float):
        self.missing = missing
        super().__init__(
            f"after {timeout} s, {len(missing)} liveliness token(s) still missing: {', '.join(missing)}"
        )


def _cover(keys: list[str]) -> list[str]:
    """Key expressions that together match every key: their common chunks + ``/**`` when they
    share any, else each key on its own."""
    if len(keys) == 1:
        return keys
    split = [k.split("/") for k in keys]
    common: list[str] = []
    for chunks in zip(*split):
        if any(c != chunks[0] for c in chunks):
            break
        common.append(chunks[0])
    return ["/".join(common) + "/**"] if common else list(keys)


async def wait_for_tokens(session: zenoh.Session, keys: Iterable[str], timeout: float) -> None:
    """Return once every key in ``keys`` has a live token; raise :class:`TokensMissing` naming the
    absent ones after ``timeout`` [s]. A token that appears and vanishes again counts as absent.
    Waits without polling; for a launcher waiting on the processes it started."""
    wanted = sorted(set(keys))
    for k in wanted:
        if "*" in k or "$" in k:
            raise ValueError(f"{k!r} is a pattern; wait_for_tokens takes concrete keys")
        zenoh.KeyExpr(k)  # raises ZError on an invalid key
    wakeup = Wakeup()
    events: BoundedFifo[TokenEvent] = BoundedFifo(capacity=max(1024, 4 * len(wanted)), wakeup=wakeup)
    alive: set[str] = set()
    subscribers = [watch_tokens(session, expr, events) for expr in _cover(wanted)]
    try:
        async with asyncio.timeout(timeout):
            while True:
                for ev in events.drain():
                    (alive.add if ev.alive else alive.discard)(ev.key)
                if alive.issuperset(wanted):
                    return
                await wakeup.wait()
    except TimeoutError:
        raise TokensMissing([k for k in wanted if k not in alive], timeout) from None
    finally:
        for sub in subscribers:
            sub.undeclare()
