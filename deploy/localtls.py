"""A local run authenticated like a deployment: one certificate per process, deny-by-default rules.

``tether run`` (``deploy/local.py``) calls :func:`prepare` before it starts anything, unless
``--insecure``. It makes, with ``deploy/pki.py`` (the ``openssl`` command), a throw-away CA and one
ECDSA key and certificate per process of the run (``CN = <process>.<ns>``, as ``tether deploy-gen``
does), plus the operator's (``control-0``), and then **deletes the CA's key**: nothing more can be
signed for this run once it has started. The access rules are ``deploy/acl.py``'s for the mission
(a ``[payload]`` mission's world process gets the plants' keys, see :func:`grants`). Everything goes
into ``DIR/tls/`` (``DIR`` is ``--out``):

* ``ca.crt``; ``<process>.crt`` and ``<process>.key`` (mode 0600) for ``router``, ``leader-<id>``,
  ``agent-<i>``, ``plant-<i>`` (or ``world-0``), ``recorder-0`` and ``control-0``;
* ``<process>.json5``: each child's whole Zenoh configuration (``--zenoh-config``): TLS only
  (``transport/link/protocols = ["tls"]``), mTLS, the name of the router checked on connect, the
  lease; in a ``mesh`` every peer listens and enforces the rules too;
* ``control-0.json5``: the **operator identity** for tools that attach to the run through the
  router's ``--listen`` endpoints: ``tether land|estop|netem-set --ns NS --zenoh-config
  DIR/tls/control-0.json5``. It connects to the first ``--listen`` endpoint (or to the launcher's
  loopback endpoint without one), and may do what a deployment's ``control-0`` may: start, tick,
  land/estop orders, netem queries.

The router is the launcher's own session (its configuration, ``router.json5``, is kept for
reference). Pure apart from the files and the ``openssl`` runs (a few tens of milliseconds each,
run four at a time).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from deploy import acl, pki
from deploy.hosts import is_ip
from tether import mission as ms
from tether import transport as tp
from tether import wire

CERT_DAYS = 2
"""A run's certificates expire after this many days (an open link is never cut at expiry)."""


def name_of(role: str, nid: int) -> str:
    """Identity (and file stem) of process ``role``/``nid``: ``agent-3``."""
    return f"{role}-{nid}"


def grants(m: ms.Mission, ns: str) -> list[acl.Grant]:
    """The deployment's grants for ``m``; for a ``[payload]`` mission, whose vehicles live in one
    world process, the plants' grants become ``world-0``'s, and the recorder may also hear the
    world's state."""
    gs = acl.grants(m, ns)
    if m.payload is None:
        return gs
    k = wire.Keys(ns)
    plants = [g for g in gs if g.name.startswith("plant-")]
    world = acl.Grant(
        "world-0",
        publish=(*(p for g in plants for p in g.publish), k.topic("world", 0, "state")),
        subscribe=tuple(dict.fromkeys(s for g in plants for s in g.subscribe)),
        tokens=(k.token("world", 0), *(t for g in plants for t in g.tokens)),
        watch=(k.tokens,),
        sees=tuple(dict.fromkeys(s for g in plants for s in g.sees)),
    )
    out = []
    for g in gs:
        if g.name.startswith("plant-"):
            continue
        if g.name == "recorder-0":
            g = dataclasses.replace(g, subscribe=(*g.subscribe, k.topic("world", 0, "state")))
        out.append(g)
    return [*out, world]


LIMIT_FACTOR = 20
"""Real time: a listener passes at most this many times the mission's rate of messages per second
on each key a process publishes, per link; one sample per period is what a stream sends."""


CONTROL_RATE = 50.0
"""Real time: messages per second per link on the start and the operator's order keys."""


def ingress_limits(m: ms.Mission, ns: str, streams: bool = True) -> tuple[tuple[str, float], ...]:
    """The listeners' per-link ingress limits of a real-time run of ``m`` (``downsampling``): the start
    and the operator's orders at :data:`CONTROL_RATE` and, with ``streams`` (the launcher's choice in
    every mode), each other published key of the run at :data:`LIMIT_FACTOR` times the rate. The price
    of the stream limits: Zenoh's downsampling passes one message per ``1/freq`` window, so the backlog
    a healed link or a loaded machine delivers at once is cut to its first (measured, Section 4, 8 s,
    a 1 s partition of agent 3, load average 10-13: 5640 and 5941 of 7209 samples recorded, 66 of agent
    3's 201 from the cut to 1 s after; without them 7116-7156 of 7209, 201 of 201). They stay on, even
    authenticated (where the access rules already keep anyone but a stream's own process off its key),
    because the formation flew worse without them on a loaded machine: RMS of ||xi|| over 7-14 s of
    20 s authenticated real-time runs, 0.443 and 0.442 m with them (the reference simulator: 0.441 m),
    17.3, 0.70 and 0.99 m without (one run each, load average 8-16). A flood on one of these keys,
    from any one session, reaches the subscribers at that rate at most, decided in Zenoh's threads
    before any Python callback, while every other session's link keeps its own budget. (Not in
    lockstep, whose ticks go out in bursts.) Exact keys only: with zenoh 1.10.2, a wildcard rule
    beside them (``tether/<ns>/**`` for "anything else") blocked some of the exact keys' samples
    altogether (measured), so keys outside the grants are not limited; under TLS no one may
    publish on them anyway."""
    k = wire.Keys(ns)
    control = {k.start: CONTROL_RATE, k.safety: CONTROL_RATE}  # one start; an order is 6 copies over 0.5 s
    keys = sorted({x for g in grants(m, ns) if g.name != "router" for x in g.publish})
    return tuple((x, control.get(x, LIMIT_FACTOR * m.rate)) for x in keys if streams or x in control)


def _host_of(endpoint: str) -> str | None:
    """The host of ``tls/<host>:<port>``, or None for a wildcard bind."""
    host = endpoint.split("/", 1)[1].rsplit(":", 1)[0].strip("[]")
    return None if host in ("0.0.0.0", "::") else host


def problems(listen: tuple[str, ...], vehicle_connect: dict[int, str]) -> list[tuple[str, str]]:
    """What cannot run authenticated, as ``(option, message)``; empty when all can."""
    out: list[tuple[str, str]] = []
    try:
        pki.openssl()
    except pki.PkiError as exc:
        out.append(("openssl", f"{exc}; it makes this run's certificates (local runs use mTLS by default). "
                               "Pass --insecure to run without authentication"))
    for ep in listen:
        if not ep.startswith("tls/"):
            out.append((f"--listen {ep}", "runs authenticated take TLS endpoints only: write "
                                          f"tls/{ep.split('/', 1)[-1]} (tools then attach with --zenoh-config "
                                          "DIR/tls/control-0.json5), or pass --insecure"))
    for nid in vehicle_connect:
        out.append((f"--vehicle-connect {nid}", "an endpoint of your own (an on-board router) holds none of this "
                                                "run's certificates, so it cannot join an authenticated run: pass "
                                                "--insecure (or deploy with tether deploy-gen)"))
    return out


@dataclass
class Security:
    """This run's identities (see the module docstring)."""

    dir: Path
    ns: str
    lease: float
    access: dict[str, Any]
    router_endpoint: str
    seconds: float = 0.0
    """How long making the identities took [s]."""
    identities: int = 0
    """Certificates made (every process, the router and the operator)."""
    configs: dict[str, Path] = field(default_factory=dict)
    limits: tuple[tuple[str, float], ...] = ()
    """Ingress rate limits of every listener (``tether.transport.ZenohSettings.ingress_limits``)."""

    def tls(self, name: str, listening: bool) -> dict[str, Any]:
        d = self.dir
        out: dict[str, Any] = {"root_ca_certificate": str(d / "ca.crt"), "enable_mtls": True,
                               "verify_name_on_connect": True,
                               "connect_certificate": str(d / f"{name}.crt"),
                               "connect_private_key": str(d / f"{name}.key")}
        if listening:
            out |= {"listen_certificate": str(d / f"{name}.crt"), "listen_private_key": str(d / f"{name}.key")}
        return out

    def profile(self, name: str, mode: str, connect: list[str], listen: list[str]) -> dict[str, Any]:
        strategy = {"peer": {"to_router": "always", "to_peer": "greater-zid"}}
        conf: dict[str, Any] = {
            "mode": mode, "listen": {"endpoints": listen},
            "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": True, "autoconnect_strategy": strategy}},
            "transport": {"link": {"protocols": ["tls"], "tx": {"lease": max(1, round(self.lease * 1000)),
                                                                 "keep_alive": 4},
                                   "tls": self.tls(name, bool(listen))}},
        }
        if mode != "router":
            conf["connect"] = {"endpoints": connect}
        if listen:
            conf["access_control"] = self.access
            if self.limits:
                conf["downsampling"] = tp.downsampling(self.limits)
        return conf

    def write(self, name: str, conf: dict[str, Any], note: str) -> Path:
        path = self.dir / f"{name}.json5"
        path.write_text(f"// {note}; written by tether run for this run only.\n" + json.dumps(conf, indent=2) + "\n")
        self.configs[name] = path
        return path

    def router(self, listen: list[str]) -> Path:
        return self.write("router", self.profile("router", "router", [], listen), "the launcher's router")

    def child(self, role: str, nid: int, connect: str, listen: str | None = None) -> Path:
        """The configuration file of child ``role``/``nid``, connecting to ``connect`` (the router, or
        a relay in front of it), listening on ``listen`` (a mesh peer)."""
        name = name_of(role, nid)
        mode = "client" if listen is None else "peer"
        return self.write(name, self.profile(name, mode, [connect], [] if listen is None else [listen]),
                          f"{name} ({mode})")


def prepare(m: ms.Mission, ns: str, out: Path, members: list[tuple[str, int]], router_endpoint: str,
            listen: tuple[str, ...], lease: float, limits: tuple[tuple[str, float], ...] = ()) -> Security:
    """Make this run's CA, identities and the operator's configuration in ``out/tls`` (replacing an
    earlier run's there); the CA's key is deleted before returning. Raises :class:`~deploy.pki.PkiError`."""
    t0 = time.monotonic()
    d = out / "tls"
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    d.chmod(0o700)
    access = acl.access_control(grants(m, ns), ns)
    sec = Security(d.resolve(), ns, lease, access, router_endpoint, limits=limits)
    router_hosts = ["127.0.0.1", *(h for ep in listen if (h := _host_of(ep)) is not None)]
    with tempfile.TemporaryDirectory(prefix="tether-ca-") as tmp:
        ca = pki.make_ca(Path(tmp), f"tether run {ns} CA", CERT_DAYS)
        shutil.copyfile(ca.cert, d / "ca.crt")
        who = [("router", router_hosts), ("control-0", ["127.0.0.1"]),
               *((name_of(r, i), ["127.0.0.1"]) for r, i in members)]
        with ThreadPoolExecutor(max_workers=4) as pool:  # openssl runs in its own process: overlap them
            for f in [pool.submit(pki.issue_one_step, ca, d, name, acl.common_name(name, ns), hosts, CERT_DAYS)
                      for name, hosts in who]:
                f.result()
    # the CA's key is gone with the temporary directory: nothing else can be signed for this run
    sec.router([router_endpoint, *listen])
    operator_to = listen[0] if listen else router_endpoint
    if operator_to.startswith("tls/") and _host_of(operator_to) is None:
        operator_to = "tls/127.0.0.1:" + operator_to.rsplit(":", 1)[1]
    sec.write("control-0", sec.profile("control-0", "client", [operator_to], []),
              "the operator identity: tether land|estop|netem-set --zenoh-config THIS_FILE")
    sec.identities = len(who)
    sec.seconds = time.monotonic() - t0
    return sec
