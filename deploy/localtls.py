"""A local run authenticated like a deployment: one certificate per process, deny-by-default rules.

``tether run`` (``deploy/local.py``) calls :func:`prepare` before it starts anything, unless
``--insecure``. It makes, with ``deploy/pki.py`` (the ``openssl`` command), a throw-away CA and one
ECDSA key and certificate per process of the run (``CN = <process>.<ns>``, as ``tether deploy-gen``
does), plus the operator gateway's (``gateway``), and a second throw-away CA, the **operator CA**,
which signs the operator's certificate (``control-0``) alone; then it **deletes both CAs' keys**:
nothing more can be signed for this run once it has started. The access rules are
``deploy/acl.py``'s for the mission (a ``[payload]`` mission's world process gets the plants' keys,
see :func:`grants`). Everything goes into ``DIR/tls/`` (``DIR`` is ``--out``):

* ``ca.crt``, ``operator-ca.crt``; ``<process>.crt`` and ``<process>.key`` (mode 0600) for ``router``,
  ``gateway``, ``leader-<id>``, ``agent-<i>``, ``plant-<i>`` (or ``world-0``), ``recorder-0`` and
  ``control-0``;
* ``<process>.json5``: each child's whole Zenoh configuration (``--zenoh-config``): TLS only
  (``transport/link/protocols = ["tls"]``), mTLS, the name of the router checked on connect, the
  lease; in a ``mesh`` every peer listens and enforces the rules too;
* ``control-0.json5``: the **operator identity** for tools that attach to the run:
  ``tether land|estop|netem-set --ns NS --zenoh-config DIR/tls/control-0.json5``. It may do what a
  deployment's ``control-0`` may (start, tick, land/estop orders, netem queries), through the
  operator gateway only.

**Two routers.** The control router, the launcher's own session (its configuration ``router.json5``
is kept for reference), carries the run's processes and listens on loopback only; it trusts
``ca.crt`` alone, so the operator's certificate (signed by the operator CA) cannot even open a link
to it. Tools attach to the **operator gateway** instead (:func:`start_gateway`): a second router
process, ``python -m deploy.router --priority P``, listening on the ``--listen`` endpoints (or a free
loopback port without any), linked to the control router under its own identity ``gateway``, which
holds there the operator's rights and nothing more. It runs one ``SCHED_RR`` step below the control
processes (:func:`tether.sched.gateway_priority`; the normal policy when they run at it): above
every normal process, so that an order reaches the swarm on a host busy with other work, and below
every control loop, so that an operator link's flood (TLS, decoding, the access and limit checks of
every message) never delays one. It applies the operator's access rules and the order keys'
ingress limits (:data:`CONTROL_RATE` a link) itself and passes on what is left: the control router
sees a flood at :data:`CONTROL_RATE` at most.

Pure apart from the files, the ``openssl`` runs (a few tens of milliseconds each, run four at a
time) and :func:`start_gateway`.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from deploy import acl, pki
from deploy.hosts import is_ip
from tether import mission as ms
from tether import safefs
from tether import transport as tp
from tether import wire

CERT_DAYS = 2
"""A run's certificates expire after this many days (an open link is never cut at expiry)."""


def name_of(role: str, nid: int) -> str:
    """Identity (and file stem) of process ``role``/``nid``: ``agent-3``."""
    return f"{role}-{nid}"


def grants(m: ms.Mission, ns: str, world: bool = False) -> list[acl.Grant]:
    """The deployment's grants for ``m``; where the vehicles live in one world process (a
    ``[payload]`` mission, or ``world``: ``--shared-plants``), the plants' grants become
    ``world-0``'s, and with a payload the recorder may also hear the world's state."""
    gs = acl.grants(m, ns)
    if m.payload is None and not world:
        return gs
    k = wire.Keys(ns)
    plants = [g for g in gs if g.name.startswith("plant-")]
    payload = (k.topic("world", 0, "state"),) if m.payload is not None else ()
    world_grant = acl.Grant(
        "world-0",
        publish=(*(p for g in plants for p in g.publish), *payload),
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
            g = dataclasses.replace(g, subscribe=(*g.subscribe, *payload))
        out.append(g)
    return [*out, world_grant]


GATEWAY = "gateway"
"""Identity of the operator gateway, the router process that tools attach to."""
OPERATOR = "control-0"
"""The operator's identity."""


def router_grants(m: ms.Mission, ns: str, world: bool = False) -> list[acl.Grant]:
    """The control router's grants: :func:`grants`, with the operator's rights held by the gateway's
    identity (no ``control-0`` subject: its certificate is refused anyway, see the module docstring)."""
    return [dataclasses.replace(g, name=GATEWAY) if g.name == OPERATOR else g for g in grants(m, ns, world)]


def gateway_grants(m: ms.Mission, ns: str) -> list[acl.Grant]:
    """The gateway's grants: the operator's, and the control router's (its link to the run)."""
    return [g for g in grants(m, ns) if g.name in ("router", OPERATOR)]


LIMIT_FACTOR = 20
"""Real time: a listener passes at most this many times the mission's rate of messages per second
on each key a process publishes, per link; one sample per period is what a stream sends. Tried and
not kept: 100 (a window of 0.2 ms at 50 Hz instead of 1 ms), against the samples real-time rings of
16 agents lose (most often the leader's or a plant's of tick 1): 5 of 13 runs lost samples at 100,
11 of 34 at 20, and 1 of 5 with the limit lifted altogether."""


CONTROL_RATE = 50.0
"""Real time: messages per second per link on the start and the operator's order keys."""


def ingress_limits(m: ms.Mission, ns: str, streams: bool = True) -> tuple[tuple[str, float], ...]:
    """The listeners' per-link ingress limits of a real-time run of ``m`` (``downsampling``): the start
    and the operator's orders at :data:`CONTROL_RATE` and, with ``streams`` (the launcher's choice in
    every mode), each other published key a control loop hears at :data:`LIMIT_FACTOR` times the rate
    (not :func:`recorder_only`'s). The price of the stream limits: Zenoh's downsampling passes one
    message per ``1/freq`` window, so the backlog a healed link or a loaded machine delivers at once is
    cut to its first (docs/deploy.md, "Floods"), and two samples a loaded publisher sends in one batch
    lose the second (a ring of 16 at 50 Hz: 3 of 6 runs lost 1-8 samples with the limits, 0 of 5
    without). They stay on, even authenticated (where the access rules already keep anyone but a
    stream's own process off its key), as the flood defence. Whether the formation flies better with
    them on a loaded machine is not settled: RMS of ||xi|| over 7-14 s of 20 s authenticated real-time
    runs of Section 4 was 0.443 and 0.442 m with them (the reference simulator: 0.441 m) and 17.3, 0.70
    and 0.99 m without (one run each, load average 8-16); beside two CPU-bound
    processes, 0.69, 1.11 and 1.20 m with them and 0.46, 0.74 and 0.45 m without. A flood on one of these keys, from any one session,
    reaches the subscribers at that rate at most, decided in Zenoh's threads before any Python
    callback, while every other session's link keeps its own budget. (Not in lockstep, whose ticks go
    out in bursts.) Exact keys only: with zenoh 1.10.2, a wildcard rule beside them
    (``tether/<ns>/**`` for "anything else") blocked some of the exact keys' samples altogether
    (measured), so keys outside the grants are not limited; under TLS no one may publish on them
    anyway."""
    k = wire.Keys(ns)
    control = {k.start: CONTROL_RATE, k.safety: CONTROL_RATE}  # one start; an order is 6 copies over 0.5 s
    keys = sorted({x for g in grants(m, ns) if g.name != "router" for x in g.publish})
    recorded = set(recorder_only(m, ns))
    return tuple((x, control.get(x, LIMIT_FACTOR * m.rate)) for x in keys
                 if x in control or (streams and x not in recorded))


def recorder_only(m: ms.Mission, ns: str) -> list[str]:
    """The published keys that no process of the control loop subscribes to, only the recorder (and
    the operator's tools): each agent's telemetry, a world's state. They carry no ingress limit, so
    that the backlog a healed link releases reaches the recording whole (Zenoh's downsampling keeps one
    message per window and no burst: with the limit, 5 of agent 3's 200 telemetry samples from a 1 s
    stall to 1 s after it reached the recording, without it 200 of 200; tests/test_partition.py). What bounds them instead:
    under TLS the access rules, which let only a stream's own process publish on it, and in every mode
    the recorder's decoding budget (2 s of samples saved, ``tether/node.py``), away from any control
    loop. The keys the control loops hear keep their limits."""
    gs = grants(m, ns)
    heard = [zenoh.KeyExpr(s) for g in gs if g.name not in ("router", OPERATOR, "recorder-0") for s in g.subscribe]
    rec = [zenoh.KeyExpr(s) for g in gs if g.name == "recorder-0" for s in g.subscribe]
    keys = sorted({x for g in gs if g.name != "router" for x in g.publish})
    return [x for x in keys if not any(h.intersects(zenoh.KeyExpr(x)) for h in heard)
            and any(r.intersects(zenoh.KeyExpr(x)) for r in rec)]


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
    gateway_access: dict[str, Any] = field(default_factory=dict)
    """The operator gateway's access rules."""
    gateway_limits: tuple[tuple[str, float], ...] = ()
    """The operator gateway's ingress limits (the order keys)."""
    gateway_endpoints: list[str] = field(default_factory=list)
    """Where the operator gateway listens: the ``--listen`` endpoints, or a free loopback port."""
    files: safefs.Dir | None = None
    """The directory being made by :func:`prepare` (files go there until it takes its name)."""

    def tls(self, name: str, listening: bool, root: str = "ca.crt") -> dict[str, Any]:
        d = self.dir
        out: dict[str, Any] = {"root_ca_certificate": str(d / root), "enable_mtls": True,
                               "verify_name_on_connect": True,
                               "connect_certificate": str(d / f"{name}.crt"),
                               "connect_private_key": str(d / f"{name}.key")}
        if listening:
            out |= {"listen_certificate": str(d / f"{name}.crt"), "listen_private_key": str(d / f"{name}.key")}
        return out

    def profile(self, name: str, mode: str, connect: list[str], listen: list[str], root: str = "ca.crt",
                access: dict[str, Any] | None = None,
                limits: tuple[tuple[str, float], ...] | None = None) -> dict[str, Any]:
        strategy = {"peer": {"to_router": "always", "to_peer": "greater-zid"}}
        conf: dict[str, Any] = {
            "mode": mode, "listen": {"endpoints": listen},
            "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": True, "autoconnect_strategy": strategy}},
            "transport": {"link": {"protocols": ["tls"], "tx": {"lease": max(1, round(self.lease * 1000)),
                                                                 "keep_alive": 4},
                                   "tls": self.tls(name, bool(listen), root)}},
        }
        if mode != "router":
            conf["connect"] = {"endpoints": connect}
        else:
            conf["transport"]["link"]["tx"]["queue"] = {"size": dict(tp.ROUTER_TX_QUEUE)}
            if connect:  # a router linked to another: open only once linked, or fail
                conf["connect"] = {"endpoints": connect, "timeout_ms": 10_000, "exit_on_failure": True}
        if listen:
            conf["access_control"] = self.access if access is None else access
            limits = self.limits if limits is None else limits
            if limits:
                conf["downsampling"] = tp.downsampling(limits)
        return conf

    def write(self, name: str, conf: dict[str, Any], note: str) -> Path:
        """Write ``<name>.json5`` into :attr:`dir` (made exclusively, following no link)."""
        text = f"// {note}; written by tether run for this run only.\n" + json.dumps(conf, indent=2) + "\n"
        if self.files is not None:
            path = self.files.create(f"{name}.json5", text.encode(), 0o600)
        else:
            with safefs.Dir.open(self.dir) as d:
                path = d.create(f"{name}.json5", text.encode(), 0o600)
        self.configs[name] = self.dir / path.name
        return self.configs[name]

    def router(self, listen: list[str]) -> Path:
        return self.write("router", self.profile("router", "router", [], listen), "the launcher's router")

    def gateway(self) -> Path:
        """The operator gateway's configuration: a router on :attr:`gateway_endpoints`, linked to the
        control router, trusting both CAs (the run's, for that link; the operator CA, for tools)."""
        conf = self.profile(GATEWAY, "router", [self.router_endpoint], self.gateway_endpoints,
                            root="gateway-ca.crt", access=self.gateway_access, limits=self.gateway_limits)
        conf["scouting"]["gossip"] = {"enabled": False}  # not advertised: a mesh's peers link to the control router
        return self.write(GATEWAY, conf, "the operator gateway (python -m deploy.router)")

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
    earlier run's there, or a link by that name, which is not followed); the CA's key is deleted
    before returning. ``out`` is a real path (:func:`tether.safefs.make_out`). The directory is
    built with mode 0700 under a random name, every file made exclusively (keys mode 0600), then
    renamed to ``tls``. Raises :class:`~deploy.pki.PkiError`, or :class:`OSError` for a file."""
    t0 = time.monotonic()
    with safefs.Dir.open(out) as top:
        made = top.fresh("tls")  # private, under a random name until complete: nothing to swap midway
        try:
            sec = _populate(m, ns, out / "tls", made, members, router_endpoint, listen, lease, limits)
            made.commit()
        except BaseException:
            made.discard()
            raise
        finally:
            made.close()
    sec.files = None
    sec.seconds = time.monotonic() - t0
    return sec


def _populate(m: ms.Mission, ns: str, final: Path, d: safefs.Dir, members: list[tuple[str, int]],
              router_endpoint: str, listen: tuple[str, ...], lease: float,
              limits: tuple[tuple[str, float], ...]) -> Security:
    """:func:`prepare`'s files, written into ``d`` (which becomes ``final``)."""
    access = acl.access_control(router_grants(m, ns, world=("world", 0) in members), ns)
    sec = Security(final, ns, lease, access, router_endpoint, limits=limits,
                   gateway_access=acl.access_control(gateway_grants(m, ns), ns),
                   gateway_limits=ingress_limits(m, ns, streams=False),
                   gateway_endpoints=list(listen) or [f"tls/127.0.0.1:{tp.free_tcp_port()}"], files=d)
    gateway_hosts = ["127.0.0.1", *(h for ep in listen if (h := _host_of(ep)) is not None)]
    with tempfile.TemporaryDirectory(prefix="tether-ca-") as tmp:
        ca = pki.make_ca(Path(tmp) / "run", f"tether run {ns} CA", CERT_DAYS)
        operator_ca = pki.make_ca(Path(tmp) / "operator", f"tether run {ns} operator CA", CERT_DAYS)
        d.create("ca.crt", ca.cert.read_bytes(), 0o644)
        d.create("operator-ca.crt", operator_ca.cert.read_bytes(), 0o644)
        d.create("gateway-ca.crt", ca.cert.read_bytes() + operator_ca.cert.read_bytes(), 0o644)
        who = [(ca, "router", ["127.0.0.1"]), (ca, GATEWAY, gateway_hosts), (operator_ca, OPERATOR, ["127.0.0.1"]),
               *((ca, name_of(r, i), ["127.0.0.1"]) for r, i in members)]
        with ThreadPoolExecutor(max_workers=4) as pool:  # openssl runs in its own process: overlap them
            for f in [pool.submit(pki.issue_one_step, by, d, name, acl.common_name(name, ns), hosts, CERT_DAYS)
                      for by, name, hosts in who]:
                f.result()
    # the CAs' keys are gone with the temporary directory: nothing else can be signed for this run
    sec.router([router_endpoint])
    sec.gateway()
    operator_to = sec.gateway_endpoints[0]
    if _host_of(operator_to) is None:
        operator_to = "tls/127.0.0.1:" + operator_to.rsplit(":", 1)[1]
    sec.write(OPERATOR, sec.profile(OPERATOR, "client", [operator_to], []),
              "the operator identity: tether land|estop|netem-set --zenoh-config THIS_FILE")
    sec.identities = len(who)
    return sec


GATEWAY_UP = "listening on"
"""What ``deploy/router.py`` logs once it listens and is linked to the control router."""


def start_gateway(sec: Security, log_path: Path, env: dict[str, str], priority: int = 0) -> subprocess.Popen[bytes]:
    """Start the operator gateway (``python -m deploy.router --priority P``) of ``sec``, logging to
    ``log_path``; ``P`` is :func:`tether.sched.gateway_priority` of the control processes' (0: the
    normal policy; a priority the system refuses falls back to it with a warning in the log). It links to the control router, which must be listening already. Does not wait:
    see :func:`wait_gateway`. The caller stops it (SIGTERM)."""
    with safefs.Dir.open(log_path.parent) as d, d.open_log(log_path.name) as fh:
        return subprocess.Popen([sys.executable, "-m", "deploy.router", "--priority", str(priority), "--watch-pid", str(os.getpid()),
                                 "--config", str(sec.configs[GATEWAY])], stdin=subprocess.DEVNULL, stdout=fh,
                                stderr=subprocess.STDOUT, env=env, start_new_session=True)


async def wait_gateway(proc: subprocess.Popen[bytes], log_path: Path, timeout: float) -> None:
    """Return once the gateway listens and is linked to the control router; ``RuntimeError`` with
    its log's last lines if it exits or does not within ``timeout`` [s]."""
    deadline = time.monotonic() + timeout
    while True:
        text = log_path.read_text(errors="replace") if log_path.exists() else ""
        if GATEWAY_UP in text:
            return
        if proc.poll() is not None or time.monotonic() > deadline:
            why = f"exited with {proc.returncode}" if proc.poll() is not None else f"not up after {timeout:g} s"
            tail = "\n".join(text.splitlines()[-5:])
            raise RuntimeError(f"the operator gateway {why} ({log_path}):\n{tail}")
        await asyncio.sleep(0.05)


def stop_gateway(proc: subprocess.Popen[bytes], grace: float = 5.0) -> int:
    """SIGTERM the gateway, SIGKILL it after ``grace`` [s]; its exit status."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode
