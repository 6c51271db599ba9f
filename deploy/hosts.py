"""The hosts file of a companion-computer deployment: where every process of a mission runs.

A strict, versioned TOML schema (msgspec, unknown fields are errors), checked against the mission
by :func:`plan`, which returns one :class:`Placement` per process. Every error names the field by
its path in the file, an ``[[agents]]`` table by its agent's id (``agent 3.address``,
``routers[1].connect[0]``), and says how to fix it, as the mission file does.

One ``[router]`` (a single site), or several ``[[routers]]`` with a ``name`` each, linked router to
router (``connect``: a tree reaching the leader's router), every other host naming its router.

Without a hosts file (:func:`plan` with ``hosts=None``) every host gets a placeholder name
(``tether-router``, ``tether-leader``, ``tether-recorder``, ``tether-agent-<i>``) that the site's
DNS or ``/etc/hosts`` must resolve, and the network is a star of clients around the router.

A Crazyflie has no companion computer: its plant drives it through a radio on the ground. Every
vehicle whose plant is ``crazyflie`` is therefore flown from the radio host (``[radio]``, default
the leader's host), one process per dongle (:func:`plant.radio.dongles`: cflib shares a Crazyradio
only among the links of one process), each vehicle still a plant of its own on the wire (its own
identity and keys). Its agent runs on its ``[[agents]]`` host where the file lists one, else on the
radio host too.

The format, field by field, is in ``docs/deploy.md``.
"""

from __future__ import annotations

import difflib
import ipaddress
import posixpath
import re
import tomllib
import unicodedata
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import msgspec

from deploy import acl
from tether import mission as ms
from tether.schema import Problems, SchemaError, Strict, read_issue

HOSTS_VERSION = 1
"""The hosts-file version this release reads."""

Network = Literal["client", "peer"]


class Host(Strict, frozen=True):
    """A machine that runs one or more of the mission's processes."""

    address: str
    """IP address or DNS name the other hosts dial (and that goes into the host's certificates)."""
    port: int | None = None
    """TLS port this host's listener uses (the router; every node in ``peer`` networks). Default: the
    file's ``port`` (an agent host's plant listens on ``port + 1``)."""
    bind: str | None = None
    """Local address to listen on; default ``address`` (so that the advertised locator matches the
    certificate's name)."""


class NodeHost(Host, frozen=True):
    """A host of tether processes (not a router): which router its processes connect to."""

    router: str | None = None
    """``name`` of the ``[[routers]]`` entry its processes connect to (two sites); default the first
    router. Not used with a single ``[router]``."""


class RouterHost(Host, kw_only=True, frozen=True):
    """One router of a deployment with several sites (``[[routers]]``)."""

    name: str
    """The site's name (``ground``, ``field``): the host directory is ``router-<name>``, the process
    ``router-<name>``, its certificate's CN ``router-<name>.<ns>``."""
    connect: list[str] = []
    """Names of the routers this one dials (router-to-router links, TLS with the same mTLS and access
    rules); every link is listed once, on one side, and the links form a tree (no loop)."""


class AgentHost(NodeHost, kw_only=True, frozen=True):
    """The companion computer of one vehicle: agent ``id`` and its plant."""

    id: int


class RecorderHost(NodeHost, kw_only=True, frozen=True):
    out: str = "/var/lib/tether/runs"
    """Directory the recorder writes ``run.npz`` into, on that host."""


class HostsFile(Strict, frozen=True):
    version: int
    network: Network = "client"
    """``client``: every process is a client of the router (a star; only the router listens).
    ``peer``: every process is a peer that listens on its host and also connects to the router,
    which relays where two peers have no direct link (multi-hop)."""
    ns: str | None = None
    """Key namespace (``tether/<ns>/...``); default: the mission's name."""
    port: int = 7447
    """Default TLS port of every listener."""
    lease: float = 2.0
    """Zenoh link lease [s]: a frozen or partitioned process is seen gone after it."""
    connect_timeout: float = 30.0
    """How long a client retries its connection to the router at start [s] before failing (its
    service then restarts it); a peer opens at once and keeps dialling in the background."""
    cert_days: int = 365
    """Validity of the certificates issued [days]."""
    config_dir: str = "/etc/tether"
    """Where each host's files live on that host; ``{host}`` is replaced by the host's name (useful
    to try a whole deployment on one machine)."""
    tether: str = "/opt/tether/venv/bin/tether"
    """The ``tether`` command on the hosts."""
    python: str = "/opt/tether/venv/bin/python"
    """The Python that has tether installed on the hosts (runs the router and the start command)."""
    user: str = "tether"
    """Unix user the services run as."""
    router: Host | None = None
    """The one router of a single-site deployment (host directory ``router``)."""
    routers: list[RouterHost] | None = None
    """Several routers linked router-to-router (two sites, e.g. a ground station and a field router),
    instead of ``[router]``; every other host names its router (``router = "field"``)."""
    leader: NodeHost | None = None
    """The ground station: the virtual leader and the operator's start command."""
    radio: NodeHost | None = None
    """The host the Crazyradios are plugged into: every Crazyflie's plant (one process per dongle),
    and the agents of Crazyflies the file does not list. Default: the leader's host (host dir
    ``leader``); given, host dir ``radio``."""
    recorder: RecorderHost | None = None
    agents: list[AgentHost] | None = None
    """One entry per agent of the mission (a Crazyflie's may be left out: its agent then runs on the
    radio host), or none for placeholder names."""


class HostsError(SchemaError):
    """A hosts file is not valid for the mission. ``problems`` holds ``(field, message-with-fix)`` pairs."""


# --------------------------------------------------------------------------- placements
Role = Literal["router", "leader", "control", "recorder", "agent", "plant"]
ROUTER_NAME = re.compile(r"[a-z][a-z0-9]{0,23}")
"""A site's name: it goes into host directory, unit, file and certificate names."""


@dataclass(frozen=True)
class Placement:
    """One process of the deployment and where it runs."""

    role: Role
    node_id: int
    host: str
    """Name of the host directory (``router``, ``leader``, ``recorder``, ``radio``, ``agent-<i>``)."""
    address: str
    listen: str | None
    """``tls/<bind>:<port>`` when this process listens, else ``None``."""
    dial: str | None
    """``tls/<address>:<port>``, the endpoint other hosts connect to when this process listens."""
    mode: Literal["router", "peer", "client"]
    site: str = ""
    """A router's site name with several routers (``field``), else empty."""
    via: str = "router"
    """Name of the router process this process connects to (``router``, ``router-field``); for a
    router, the routers it dials, comma-separated (empty for none)."""

    @property
    def name(self) -> str:
        """File stem of this process's files: ``router``, ``router-field``, ``agent-3``, ``control-0``..."""
        if self.role == "router":
            return f"router-{self.site}" if self.site else "router"
        return f"{self.role}-{self.node_id}"

    def common_name(self, ns: str) -> str:
        """The certificate's subject CN, which the access-control rules name: ``agent-3.<ns>``."""
        return acl.common_name(self.name, ns)


@dataclass(frozen=True)
class Radio:
    """One radio host process: the Crazyflies of one dongle, flown from one process (:mod:`cli.radio`)."""

    index: int
    """Its number in the deployment (unit ``tether-radio-<index>``), in the order of its first vehicle."""
    dongle: str
    """:attr:`plant.radio.Dongle.name`: ``radio://0``, ``sim://127.0.0.1/0``, a ``usb://`` URI."""
    agents: tuple[int, ...]
    host: str
    """The host directory it runs on (``leader`` or ``radio``)."""

    @property
    def name(self) -> str:
        return f"radio-{self.index}"


@dataclass(frozen=True)
class Plan:
    """Everything the generator needs besides the mission: the hosts file's values and the placements."""

    ns: str
    hosts: HostsFile
    placements: tuple[Placement, ...]
    radios: tuple[Radio, ...] = ()
    """The radio host processes, one per dongle; every Crazyflie's plant is flown by one."""

    def radio_of(self, p: Placement) -> Radio | None:
        """The radio host process that flies plant ``p``, or None (not a Crazyflie's plant)."""
        if p.role != "plant":
            return None
        return next((r for r in self.radios if p.node_id in r.agents), None)

    @property
    def router(self) -> Placement:
        """The first router (the only one of a single site)."""
        return next(p for p in self.placements if p.role == "router")

    @property
    def routers(self) -> list[Placement]:
        return [p for p in self.placements if p.role == "router"]

    def process(self, name: str) -> Placement:
        """The placement of process ``name`` (``router-field``, ``agent-3``)."""
        return next(p for p in self.placements if p.name == name)

    def dials(self, p: Placement) -> list[str]:
        """The endpoints process ``p`` connects to: its router's; a router's, the routers it links to."""
        names = [n for n in p.via.split(",") if n]
        return [d for n in names if (d := self.process(n).dial) is not None]

    def links(self) -> list[tuple[str, str]]:
        """The router-to-router links, ``(dialler, dialled)`` router process names."""
        return [(r.name, n) for r in self.routers for n in r.via.split(",") if n]

    def neighbours(self, router: str) -> list[str]:
        """The routers linked to router process ``router`` (``router-field``), either way."""
        return [b if a == router else a for a, b in self.links() if router in (a, b)]

    def behind(self, router: str, neighbour: str) -> list[Placement]:
        """The processes (routers aside) whose messages reach ``router`` over its link to ``neighbour``:
        every process of a router on ``neighbour``'s side of that link (the links form a tree)."""
        side, todo = {neighbour}, [neighbour]
        while todo:
            here = todo.pop()
            for n in self.neighbours(here):
                if n != router and n not in side:
                    side.add(n)
                    todo.append(n)
        return [p for p in self.placements if p.role != "router" and p.via in side]

    def on(self, host: str) -> list[Placement]:
        return [p for p in self.placements if p.host == host]

    @property
    def host_names(self) -> list[str]:
        return list(dict.fromkeys(p.host for p in self.placements))

    def config_dir(self, host: str) -> str:
        return self.hosts.config_dir.replace("{host}", host)


# --------------------------------------------------------------------------- loading
def loads(text: str | bytes, source: str = "<hosts>") -> HostsFile:
    """Decode a hosts file from TOML text (types only; :func:`plan` checks it against a mission)."""
    try:
        raw = tomllib.loads(text.decode() if isinstance(text, bytes) else text)
    except tomllib.TOMLDecodeError as exc:
        raise HostsError(source, [("<file>", f"is not valid TOML: {exc}; fix the syntax there")]) from None
    except UnicodeDecodeError:
        raise HostsError(source, [("<file>", "is not UTF-8 text; save it as UTF-8")]) from None
    version = raw.get("version")
    if "version" not in raw:
        raise HostsError(source, [("version", f"is missing; add `version = {HOSTS_VERSION}` as the first line")])
    if type(version) is not int or version != HOSTS_VERSION:
        raise HostsError(source, [("version", f"is {version!r} but this release reads version {HOSTS_VERSION}; "
                                              f"set `version = {HOSTS_VERSION}` after checking docs/deploy.md")])
    try:
        return msgspec.convert(raw, type=HostsFile)
    except msgspec.ValidationError as exc:
        agents = raw.get("agents")
        ids = [a.get("id") if isinstance(a, dict) and type(a.get("id")) is int else None
               for a in agents] if isinstance(agents, list) else []
        raise HostsError(source, ms.by_id([_field_of(exc)], ids, [])) from None


def load(path: str | Path) -> HostsFile:
    path = Path(path)
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise HostsError(str(path), [("<file>", f"cannot be read ({exc.strerror}); check the path")]) from None
    return loads(text, source=str(path))


_FIELDS = {
    "": [f.encode_name for f in msgspec.structs.fields(HostsFile)],
    "router": [f.encode_name for f in msgspec.structs.fields(Host)],
    "leader": [f.encode_name for f in msgspec.structs.fields(NodeHost)],
    "radio": [f.encode_name for f in msgspec.structs.fields(NodeHost)],
    "recorder": [f.encode_name for f in msgspec.structs.fields(RecorderHost)],
    "agents": [f.encode_name for f in msgspec.structs.fields(AgentHost)],
    "routers": [f.encode_name for f in msgspec.structs.fields(RouterHost)],
}


_NOUNS = {"int": "an integer", "float": "a number", "str": "a string", "bool": "a boolean", "array": "an array",
          "object": "a table"}


def _field_of(exc: msgspec.ValidationError) -> tuple[str, str]:
    """``(field path, message-with-fix)`` from a msgspec validation error."""
    issue = read_issue(exc)
    where = issue.where
    table = re.sub(r"\[\d+\]", "", where).split(".")[0] if where else ""
    if issue.kind == "unknown_field" and issue.name is not None:
        known = _FIELDS.get(table, [])
        close = difflib.get_close_matches(issue.name, known, n=1)
        fix = f"rename it to `{close[0]}` if that is what you meant, or remove it" if close else "remove it"
        return issue.field, f"is not a known field; {fix} (the fields here are {', '.join(known)})"
    if issue.kind == "missing_field" and issue.name is not None:
        example = {"address": '"192.168.1.11"', "id": "1"}.get(issue.name, "...")
        return issue.field, f"is required; add `{issue.name} = {example}` (see docs/deploy.md)"
    if issue.kind == "wrong_type" and issue.got is not None:
        want, got = issue.expected[0], issue.got
        example = {"int": "7447", "float": "2.0", "str": '"192.168.1.11"'}.get(want, "...")
        quotes = " (no quotes)" if got == "str" and want in ("int", "float") else ""
        name = where.split(".")[-1] if where else "<field>"
        return where or "<file>", (f"is {_NOUNS.get(got, got)} but must be {_NOUNS.get(want, want)}; "
                                   f"write e.g. `{name} = {example}`{quotes}")
    if issue.kind == "invalid_value" and issue.value is not None and where == "network":
        return "network", f"{issue.sentence}; use \"client\" or \"peer\""
    return where or "<file>", f"{issue.sentence}; see docs/deploy.md for this field's type"


# --------------------------------------------------------------------------- checks
_HOSTNAME = re.compile(r"(?=.{1,253}\Z)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*")


def is_ip(address: str) -> bool:
    try:
        ipaddress.ip_address(address)
    except ValueError:
        return False
    return True


def _address_problem(value: object) -> str | None:
    if not isinstance(value, str) or not value:
        return f"is {value!r}; give an IP address or a DNS name, e.g. \"192.168.1.11\""
    if is_ip(value) or _HOSTNAME.fullmatch(value):
        return None
    return (f"is {value!r}, neither an IP address nor a DNS name; write e.g. \"192.168.1.11\" or "
            "\"uav1.local\" (no scheme, no port: the port has its own field)")


NAMESPACE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,62}")
"""A deployment's key namespace: it goes into keys, certificate CNs, unit descriptions and command lines."""
USER_NAME = re.compile(r"[a-z_][a-z0-9_-]{0,31}")
"""A Unix user name as ``useradd`` takes it by default."""
PATH_MAX = 4096

_NOT_IN_PATHS = {'"': "a double quote", "'": "a single quote", "\\": "a backslash", "$": "a dollar sign"}
"""Characters refused in every path: systemd refuses quotes and backslashes in a program's path
(``systemd-analyze verify``: "Executable name contains special characters") and keeps ``$$`` there
as written; in an argument they would need escapes that every reader of the units (systemd,
``tether rehearse``) must agree on."""


def control_character(value: str) -> str | None:
    """The first character of ``value`` that is not printable text (Unicode categories C* — control,
    format such as a bidirectional override, private use, surrogate, unassigned — and the line and
    paragraph separators), described as ``U+000A at position 12``; None when there is none."""
    for k, ch in enumerate(value):
        if unicodedata.category(ch)[0] == "C" or unicodedata.category(ch) in ("Zl", "Zp"):
            return f"U+{ord(ch):04X} at position {k}"
    return None


def path_problem(value: str, program: bool = False) -> str | None:
    """Why ``value`` cannot be a path on the hosts in a unit file or a command line, with the fix; None
    when it can. A path must be absolute and normalised (no ``.``, ``..``, ``//`` or trailing ``/``),
    printable (no control character anywhere), without a quote, a backslash or a dollar sign,
    without leading or trailing space. Spaces, ``%``, ``;`` and non-ASCII letters are allowed:
    the generator quotes them (:func:`deploy.gen.exec_word`). Pure."""
    if (bad := control_character(value)) is not None:
        return (f"is {value!r}, which holds a control character ({bad}); remove it (a newline in a unit "
                "file starts another directive)")
    for ch, name in _NOT_IN_PATHS.items():
        if ch in value:
            return f"is {value!r}, which holds {name}; install into a directory whose path has none"
    if not value.startswith("/"):
        return f"is {value!r}; give an absolute path on the hosts (starting with '/'; systemd needs one)"
    if value != value.strip():
        return f"is {value!r}, with a space at its end; remove it"
    if len(value.encode()) > PATH_MAX:
        return f"is {len(value.encode())} bytes long; a path is at most {PATH_MAX}"
    parts = value.split("/")[1:]
    if ".." in parts:
        return f"is {value!r}, with '..'; write the directory it means, without '..'"
    if posixpath.normpath(value) != value:
        return f"is {value!r}, not normalised; write {posixpath.normpath(value)!r}"
    if program and value == "/":
        return f"is {value!r}; give the path of the program"
    return None


def _endpoint(address: str, port: int) -> str:
    host = f"[{address}]" if is_ip(address) and ":" in address else address
    return f"tls/{host}:{port}"


def crazyflies(m: ms.Mission) -> list[tuple[int, str]]:
    """``(agent id, URI)`` of every vehicle of ``m`` whose plant is a Crazyflie, in mission order."""
    return [(a.id, a.plant.uri) for a in m.agents if isinstance(a.plant, ms.CrazyfliePlant)]


def _default_hosts(m: ms.Mission) -> HostsFile:
    """Placeholder names; a Crazyflie's agent runs beside its radio (no companion computer)."""
    flown = {aid for aid, _ in crazyflies(m)}
    return HostsFile(
        version=HOSTS_VERSION,
        router=Host(address="tether-router"),
        leader=NodeHost(address="tether-leader"),
        recorder=RecorderHost(address="tether-recorder"),
        agents=[AgentHost(id=a, address=f"tether-agent-{a}") for a in m.agent_ids if a not in flown],
    )


def plan(m: ms.Mission, hosts: HostsFile | None = None, source: str = "<hosts>") -> Plan:
    """Check ``hosts`` against mission ``m`` and place every process; raises :class:`HostsError`
    listing every problem found. ``hosts=None`` uses placeholder host names and a star network."""
    h = hosts if hosts is not None else _default_hosts(m)
    out: Problems = []
    if m.payload is not None:
        raise HostsError(source, [("<mission> payload", "is set: a payload world simulates every vehicle and the "
                                                        "cables in one process, which cannot be split over companion "
                                                        "computers; deploy the mission without [payload] (the real "
                                                        "vehicles carry the real payload)")])
    ns = h.ns if h.ns is not None else m.name
    if not NAMESPACE.fullmatch(ns):
        field = "ns" if h.ns is not None else "<mission name>"
        out.append((field, f"is {ns!r}, not a plain name (it goes into keys, certificate names and unit "
                           "files); set `ns = \"...\"` in the hosts file to letters, digits, '_', '-' and '.', "
                           "at most 63, starting with a letter or a digit"))
    if not 1 <= h.port <= 65535:
        out.append(("port", f"is {h.port}; a TLS port is 1 to 65535 (7447 is Zenoh's)"))
    if not h.lease > 0:
        out.append(("lease", f"is {h.lease} s; the link lease must be > 0 s (1-2 s suits flight)"))
    if not h.connect_timeout > 0:
        out.append(("connect_timeout", f"is {h.connect_timeout} s; give seconds > 0, e.g. 30.0"))
    if not h.cert_days >= 1:
        out.append(("cert_days", f"is {h.cert_days}; certificates must be valid for >= 1 day"))
    for name in ("tether", "python"):
        if (problem := path_problem(getattr(h, name), program=True)) is not None:
            out.append((name, problem))
    if (problem := path_problem(h.config_dir.replace("{host}", "agent-1"))) is not None:
        out.append(("config_dir", problem.replace("agent-1", "{host}")))
    if not USER_NAME.fullmatch(h.user):
        out.append(("user", f"is {h.user!r}; give a Unix user name (lower-case letters, digits, '_' and '-', "
                            "at most 32), e.g. \"tether\""))
    if h.recorder is not None and (problem := path_problem(h.recorder.out)) is not None:
        out.append(("recorder.out", problem))

    defaults = _default_hosts(m)
    if h.router is not None and h.routers is not None:
        out.append(("routers", "is given together with [router]; keep [router] for one site, or list every router "
                               "as [[routers]] (with a name each) for several"))
    sites = h.routers if h.routers else None
    router = h.router or defaults.router
    leader = h.leader or defaults.leader
    recorder = h.recorder or defaults.recorder
    agents = h.agents if h.agents is not None else defaults.agents
    assert router is not None and leader is not None and recorder is not None and agents is not None
    if h.routers is not None and not h.routers:
        out.append(("routers", "is empty; list at least one [[routers]] table, or use [router] for one site"))

    listed: dict[int, int] = {}
    for k, a in enumerate(agents):
        if a.id in listed:
            out.append((f"agents[{k}].id", f"is {a.id}, listed twice; list each agent once"))
        elif a.id not in m.agent_ids:
            out.append((f"agents[{k}].id", f"is {a.id}, not an agent of mission {m.name!r}; "
                                           f"use one of {m.agent_ids}"))
        listed.setdefault(a.id, k)
    flown = dict(crazyflies(m))
    missing = [a for a in m.agent_ids if a not in listed and a not in flown]
    if missing:
        out.append(("agents", f"lacks agent{'s' if len(missing) > 1 else ''} {', '.join(map(str, missing))} of "
                              f"mission {m.name!r}; add one [[agents]] table per agent, e.g. "
                              f"`[[agents]] id = {missing[0]}, address = \"...\"` (only a Crazyflie's may be left "
                              "out: it runs on the radio host)"))
    if h.radio is not None and not flown:
        out.append(("radio", f"is given but mission {m.name!r} has no Crazyflie (no plant of kind \"crazyflie\"); "
                             "remove [radio]"))

    radio = h.radio or leader
    tables: list[tuple[str, Host]] = [("leader", leader), ("recorder", recorder)]
    if h.radio is not None:
        tables.append(("radio", h.radio))
    tables = ([(f"routers[{k}]", r) for k, r in enumerate(sites)] if sites else [("router", router)]) + tables
    tables += [(f"agents[{k}]", a) for k, a in enumerate(agents)]
    for where, host in tables:
        if (problem := _address_problem(host.address)) is not None:
            out.append((f"{where}.address", problem))
        if host.bind is not None and (problem := _address_problem(host.bind)) is not None:
            out.append((f"{where}.bind", problem))
        if host.port is not None and not 1 <= host.port <= (65534 if where.startswith("agents") else 65535):
            out.append((f"{where}.port", f"is {host.port}; a TLS port is 1 to 65535 (an agent host's plant "
                                         "takes port + 1)"))
    nodes: list[tuple[str, NodeHost]] = [("leader", leader), ("recorder", recorder)]
    if h.radio is not None:
        nodes.append(("radio", h.radio))
    nodes += [(f"agents[{k}]", a) for k, a in enumerate(agents)]
    via = _check_sites(sites, nodes, out)
    if out:
        raise HostsError(source, _by_id(out, agents))

    peer = h.network == "peer"
    placements: list[Placement] = []

    def place(role: Role, nid: int, host: str, where: Host, port_offset: int, listens: bool,
              mode: Literal["router", "peer", "client"], site: str = "", through: str = "router") -> None:
        port = (where.port if where.port is not None else h.port) + port_offset
        listen = _endpoint(where.bind or where.address, port) if listens else None
        dial = _endpoint(where.address, port) if listens else None
        placements.append(Placement(role, nid, host, where.address, listen, dial, mode, site, through))

    if sites:
        for r in sites:
            place("router", 0, f"router-{r.name}", r, 0, True, "router", r.name,
                  ",".join(f"router-{n}" for n in r.connect))
    else:
        place("router", 0, "router", router, 0, True, "router", "", "")
    node_mode: Literal["peer", "client"] = "peer" if peer else "client"
    place("leader", m.leader.id, "leader", leader, 0, peer, node_mode, through=via["leader"])
    place("control", 0, "leader", leader, 0, False, "client", through=via["leader"])
    place("recorder", 0, "recorder", recorder, 0, peer, node_mode, through=via["recorder"])
    by_id = {a.id: (k, a) for k, a in reversed(list(enumerate(agents)))}
    # the radio host: after the leader's listener when it is the leader's host
    radio_host, radio_via = ("radio", via["radio"]) if h.radio is not None else ("leader", via["leader"])
    next_port = [0 if h.radio is not None else 1]

    def on_radio(role: Role, aid: int) -> None:
        place(role, aid, radio_host, radio, next_port[0] if peer else 0, peer, node_mode, through=radio_via)
        next_port[0] += peer

    for aid in m.agent_ids:
        if aid in by_id:
            k, a = by_id[aid]
            place("agent", aid, f"agent-{aid}", a, 0, peer, node_mode, through=via[f"agents[{k}]"])
            if aid not in flown:
                place("plant", aid, f"agent-{aid}", a, 1, peer, node_mode, through=via[f"agents[{k}]"])
        else:
            on_radio("agent", aid)
        if aid in flown:
            on_radio("plant", aid)
    from plant import radio as radios  # pure: the grouping rule tether run uses

    groups = tuple(Radio(k, d.name, d.agents, radio_host) for k, d in enumerate(radios.dongles(list(flown.items()))))
    if peer and flown:
        top = (radio.port if radio.port is not None else h.port) + next_port[0] - 1
        if top > 65535:
            out.append(("radio.port" if h.radio is not None else "leader.port",
                        f"leaves no room: the radio host's {next_port[0]} listeners need ports up to {top} (> 65535); "
                        "give a lower port"))

    # two listeners on one socket address would fail at start on the host: say so now
    seen: dict[str, str] = {}
    for p in placements:
        if p.listen is None:
            continue
        if p.listen in seen:
            out.append((_where(p, agents, sites), f"listens on {p.listen} like {seen[p.listen]}; give one of them "
                                                  "another port or address"))
        seen.setdefault(p.listen, p.name)
    if out:
        raise HostsError(source, _by_id(out, agents))
    return Plan(ns=ns, hosts=h, placements=tuple(placements), radios=groups)


def _by_id(out: Problems, agents: list[AgentHost]) -> Problems:
    """``agents[k]…`` fields named by the agent's id, as the mission's errors are (``agent 3.address``)."""
    return ms.by_id(out, [a.id for a in agents], [])


def _check_sites(sites: list[RouterHost] | None, nodes: list[tuple[str, NodeHost]], out: Problems) -> dict[str, str]:
    """Check the routers of a several-site deployment and which router each host uses; returns the
    router process each node table (``leader``, ``agents[2]``) connects to. The router links must
    name known routers, form no loop, and join every router used to the leader's router."""
    if not sites:
        for where, host in nodes:
            if host.router is not None:
                out.append((f"{where}.router", f"is {host.router!r} but the hosts file has one [router]; remove it, or "
                                               "list the routers as [[routers]] with a name each"))
        return {where: "router" for where, _ in nodes}
    names: dict[str, int] = {}
    for k, r in enumerate(sites):
        if not ROUTER_NAME.fullmatch(r.name):
            out.append((f"routers[{k}].name", f"is {r.name!r}; give a short lower-case name of letters and digits, "
                                              "e.g. \"ground\" or \"field\" (it names files and certificates)"))
        elif r.name in names:
            out.append((f"routers[{k}].name", f"is {r.name!r}, already the name of routers[{names[r.name]}]; give "
                                              "each router its own name"))
        names.setdefault(r.name, k)
    # the links, undirected: a loop (or a link listed on both sides) makes routes ambiguous
    parent = {n: n for n in names}

    def root(n: str) -> str:
        while parent[n] != n:
            n = parent[n]
        return n

    for k, r in enumerate(sites):
        for j, other in enumerate(r.connect):
            field = f"routers[{k}].connect[{j}]"
            if other not in names:
                out.append((field, f"is {other!r}, not a router of this file; use one of "
                                   f"{', '.join(repr(n) for n in names)} (each [[routers]] table's name)"))
            elif other == r.name:
                out.append((field, f"is {other!r}, this router itself: a loop; remove it"))
            elif r.name in names and root(other) == root(r.name):
                out.append((field, f"links {r.name!r} to {other!r}, which are already linked (directly or through "
                                   "other routers): a loop; list each router-to-router link once, on one side, "
                                   "and link the routers as a tree"))
            elif r.name in names:
                parent[root(other)] = root(r.name)
    first = sites[0].name
    via: dict[str, str] = {}
    for where, host in nodes:
        name = host.router if host.router is not None else first
        if name not in names:
            out.append((f"{where}.router", f"is {name!r}, not a router of this file; use one of "
                                           f"{', '.join(repr(n) for n in names)}"))
        via[where] = f"router-{name}"
    lead = dict(nodes)["leader"].router or first
    if lead in names and not out:
        for k, r in enumerate(sites):
            if root(r.name) != root(lead):
                out.append((f"routers[{k}].connect", f"does not link router {r.name!r} to the leader's router {lead!r} "
                                                     "(directly or through other routers); add `connect = "
                                                     f"[\"{lead}\"]` to it"))
        for where, host in nodes:
            name = host.router or first
            if name in names and root(name) != root(lead):
                out.append((f"{where}.router", f"is {name!r}, which has no route to the leader's router {lead!r}: no "
                                               "router-to-router link joins them; add `connect = "
                                               f"[\"{lead}\"]` to the [[routers]] table named {name!r} (or link it "
                                               "to a router that is linked to it)"))
    return via


def _where(p: Placement, agents: list[AgentHost], sites: list[RouterHost] | None) -> str:
    if p.role in ("agent", "plant") and p.host.startswith("agent-"):
        k = next(k for k, a in enumerate(agents) if a.id == p.node_id)
        return f"agents[{k}].port"
    if p.role == "router" and sites:
        return f"routers[{next(k for k, r in enumerate(sites) if r.name == p.site)}].port"
    return f"{p.host}.port"
