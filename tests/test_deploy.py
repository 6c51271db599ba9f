"""Companion-computer deployment (``deploy/``): generated files, mTLS, access control, a real run.

Every Zenoh session here uses the generated configurations (multicast scouting off, TLS only) on
``tls/127.0.0.1:<port>`` with ports picked free at run time. The router is the real entry point
(``python -m deploy.router``) in its own process; the runtime test starts every role from the
``ExecStart`` line of its generated systemd unit. Every wait is on a condition with a timeout.

What the security tests show, each beside a counter-check that the same attack succeeds where the
protection is removed (so that they can fail):

* without a certificate of the deployment's CA (none, or one of another CA claiming agent 3's
  name) a session gets no link to the router;
* a session holding agent 2's certificate cannot move agent 3: its puts on agent 3's ``cmd`` and
  ``state`` keys never reach the processes that legitimately subscribe to them, it cannot
  eavesdrop on them, and it cannot fake plant 3's liveliness token — through the router and
  directly to a listening peer;
* a session holding an agent's certificate cannot order a land or an e-stop: its puts on the
  control key ``control/0/safety`` never reach the agents and plants that subscribe to it, while
  the operator's (``control-0``) do;
* plain TCP is refused where TLS is required.
"""

from __future__ import annotations

import asyncio
import json
import shlex
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import msgspec
import numpy as np
import pytest
import zenoh

from deploy import acl, gen, hosts, pki
from deploy import start as start_cmd
from netem import control
from tether import mission as ms
from tether import transport as tp
from tether import wire

WAIT = 5.0
"""Upper bound [s] on a wait for something that takes milliseconds on loopback."""

REPO = Path(__file__).resolve().parents[1]

MISSION = """\
version = 1
name = "trio"
dim = 2
rate = 20.0
duration = 1.0
# agent 1 hears the leader and agent 3; agent 2 hears 1; agent 3 hears 2
edges = [ { from = 4, to = 1 }, { from = 3, to = 1 }, { from = 1, to = 2 }, { from = 2, to = 3 } ]
[law]
kind = "sigma"
kp0 = 2.0
kv0 = 2.0
gamma_p = 0.05
gamma_v = 0.05
sigma = 1.0
[leader]
id = 4
p0 = [0.0, 0.0]
[[agents]]
id = 1
p0 = [1.0, 0.2]
offset = [1.0, 0.0]
[[agents]]
id = 2
p0 = [0.1, 1.0]
offset = [0.0, 1.0]
[[agents]]
id = 3
p0 = [-1.0, -0.1]
offset = [-1.0, 0.0]
[netem]
default = "ideal"  # the emulator on, bit-identical to none: tether netem-set has links to change
"""

KEYS = wire.Keys("trio")
PYTHON_ON_HOSTS = "/opt/tether/venv/bin/python"
TETHER_ON_HOSTS = "/opt/tether/venv/bin/tether"


def toml_str(s: str | Path) -> str:
    return json.dumps(str(s))  # a TOML basic string for the plain paths used here


def write_hosts(path: Path, out: Path, body: str) -> Path:
    path.write_text(f"version = 1\nconfig_dir = {toml_str(out / 'hosts' / '{host}')}\n"
                    f"tether = {toml_str(TETHER_ON_HOSTS)}\npython = {toml_str(PYTHON_ON_HOSTS)}\n{body}")
    return path


# --------------------------------------------------------------------------- helpers
class Inbox:
    """Samples handed off by a subscriber callback (payload bytes), waited on with a timeout."""

    def __init__(self) -> None:
        self.items: list[bytes] = []
        self._cond = threading.Condition()

    def put(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.items.append(sample.payload.to_bytes())
            self._cond.notify_all()

    def wait_for(self, payload: bytes, timeout: float = WAIT) -> None:
        with self._cond:
            if not self._cond.wait_for(lambda: payload in self.items, timeout):
                raise AssertionError(f"{payload!r} did not arrive within {timeout} s (got {self.items})")


class Tokens:
    """Liveliness events (key, alive) seen by a liveliness subscriber, waited on with a timeout."""

    def __init__(self) -> None:
        self.events: list[tuple[str, bool]] = []
        self._cond = threading.Condition()

    def put(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.events.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))
            self._cond.notify_all()

    def wait_for(self, key: str, timeout: float = WAIT) -> None:
        with self._cond:
            if not self._cond.wait_for(lambda: (key, True) in self.events, timeout):
                raise AssertionError(f"token {key} did not appear within {timeout} s (saw {self.events})")


def wait_matching(pub: zenoh.Publisher, timeout: float = WAIT) -> None:
    """Until ``pub`` knows of a matching subscriber (so that its puts are really sent)."""
    matched = threading.Event()
    listener = pub.declare_matching_listener(lambda status: status.matching and matched.set())
    try:
        if not (pub.matching_status.matching or matched.wait(timeout)):
            raise AssertionError(f"no subscriber matched {pub.key_expr} within {timeout} s")
    finally:
        listener.undeclare()


def cmd(sender: int, u: list[float], seq: int = 0) -> bytes:
    return wire.encode(wire.Command(sender=sender, seq=seq, k=0, t=0.0, u=u))


def config_of(dep: gen.Deployment, name: str, **json5: object) -> zenoh.Config:
    """Process ``name``'s generated configuration, with some keys replaced (``connect__endpoints=[...]``)."""
    config = tp.zenoh_config(tp.ZenohSettings(config_file=str(dep.config(name))))
    for key, value in json5.items():
        config.insert_json5(key.replace("__", "/"), json.dumps(value))
    return config


def open_as(dep: gen.Deployment, name: str, **json5: object) -> zenoh.Session:
    return zenoh.open(config_of(dep, name, **json5))


def read_json5(path: Path) -> dict:
    return json.loads("".join(line for line in path.read_text().splitlines(True) if not line.startswith("//")))


def start_router(config: Path, log: Path) -> tuple[subprocess.Popen, str]:
    """``python -m deploy.router --config CONFIG`` in its own process; returns it once it listens."""
    fh = open(log, "wb")
    proc = subprocess.Popen([sys.executable, "-m", "deploy.router", "--config", str(config)], cwd=REPO,
                            stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT)
    fh.close()
    deadline = time.monotonic() + 20.0
    while "listening on" not in log.read_text():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            proc.wait()
            raise AssertionError(f"router did not come up (exit {proc.returncode}):\n{log.read_text()}")
        time.sleep(0.05)
    zid = log.read_text().split("router ", 2)[-1].split()[0]
    return proc, zid


def stop(proc: subprocess.Popen, timeout: float = 10.0) -> int:
    proc.terminate()
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def mission_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("mission") / "trio.toml"
    path.write_text(MISSION)
    return path


@pytest.fixture(scope="module")
def client_hosts(tmp_path_factory: pytest.TempPathFactory) -> str:
    """The tables of a client (star) hosts file on loopback: the router on a free port, every host 127.0.0.1."""
    runs = tmp_path_factory.mktemp("runs")
    return f"""
[router]
address = "127.0.0.1"
port = {tp.free_tcp_port()}
[leader]
address = "127.0.0.1"
[recorder]
address = "127.0.0.1"
out = {toml_str(runs)}
"""


@pytest.fixture(scope="module")
def deployment(tmp_path_factory: pytest.TempPathFactory, mission_file: Path, client_hosts: str) -> gen.Deployment:
    root = tmp_path_factory.mktemp("deploy")
    out = root / "out"
    return gen.generate(mission_file, out, hosts=write_hosts(root / "hosts.toml", out, client_hosts))


@pytest.fixture(scope="module")
def router(deployment: gen.Deployment) -> Iterator[str]:
    """The deployment's router (``python -m deploy.router``) running; yields its zid."""
    proc, zid = start_router(deployment.config("router"), deployment.out / "router.log")
    try:
        yield zid
    finally:
        status = stop(proc)
        assert status == 0, (deployment.out / "router.log").read_text()


# --------------------------------------------------------------------------- generated files
def test_every_generated_profile_is_a_zenoh_configuration(deployment: gen.Deployment) -> None:
    files = sorted(deployment.out.glob("hosts/*/*.json5"))
    names = {p.name for p in deployment.plan.placements}
    assert {f.stem for f in files} == names == {"router", "leader-4", "control-0", "recorder-0", "agent-1",
                                                "plant-1", "agent-2", "plant-2", "agent-3", "plant-3"}
    for f in files:
        config = tp.zenoh_config(tp.ZenohSettings(config_file=str(f)))  # Zenoh's own parser
        get = lambda key: json.loads(config.get_json(key))  # noqa: E731
        p = next(p for p in deployment.plan.placements if p.name == f.stem)
        assert get("mode") == p.mode
        assert get("transport/link/protocols") == ["tls"]
        assert get("scouting/multicast/enabled") is False
        assert (get("transport/link/tx/queue/size")["interactive_high"] == 16) == (p.mode == "router")
        tls = get("transport/link/tls")
        assert tls["enable_mtls"] is True and tls["verify_name_on_connect"] is True
        for k in ("root_ca_certificate", "connect_certificate", "connect_private_key"):
            assert Path(tls[k]).is_file(), (f, k)
        pki.verify(Path(tls["root_ca_certificate"]), Path(tls["connect_certificate"]))
        assert (Path(tls["connect_private_key"]).stat().st_mode & 0o077) == 0  # keys are private
        endpoints = get("listen/endpoints") + (get("connect/endpoints") if p.mode != "router" else [])
        assert endpoints and all(e.startswith("tls/127.0.0.1:") for e in endpoints)
        assert get("access_control/enabled") is (p.mode == "router")  # only listeners enforce (client star)
    # the reviewed copy is the section the router holds
    acl_text = (deployment.out / "acl.json5").read_text()
    config = zenoh.Config.from_json5("{access_control: " + acl_text + "}")
    assert json.loads(config.get_json("access_control")) == json.loads(
        tp.zenoh_config(tp.ZenohSettings(config_file=str(deployment.config("router")))).get_json("access_control"))


def test_certificates_name_their_process_and_host(deployment: gen.Deployment) -> None:
    def show(host: str, name: str) -> str:
        crt = deployment.host_dir(host) / "tls" / f"{name}.crt"
        return subprocess.run(["openssl", "x509", "-in", str(crt), "-noout", "-subject", "-ext",
                               "subjectAltName,extendedKeyUsage,basicConstraints"],
                              capture_output=True, text=True, check=True).stdout.replace("CN = ", "CN=")

    router, agent = show("router", "router"), show("agent-3", "agent-3")
    assert "CN=router.trio" in router and "IP Address:127.0.0.1" in router  # the address clients dial
    assert "CN=agent-3.trio" in agent and "DNS:tether-agent-3" in agent  # a placeholder name (not in hosts file)
    for text in (router, agent):
        assert "CA:FALSE" in text
        assert "TLS Web Server Authentication" in text and "TLS Web Client Authentication" in text
    # the CA's key never goes to a host
    assert not list(deployment.out.glob("hosts/**/ca.key"))


def test_the_acl_grants_exactly_what_the_roles_declare(deployment: gen.Deployment) -> None:
    m = ms.load(deployment.host_dir("agent-1") / "mission.toml")
    g = {x.name: x for x in acl.grants(m, "trio")}
    a2 = g["agent-2"]
    assert a2.publish == ("tether/trio/agent/2/state", "tether/trio/agent/2/cmd", "tether/trio/agent/2/telemetry",
                          "tether/trio/agent/2/record")  # record: its co-located plant's (--colocate-plants)
    # recorded: lockstep, the launcher's word that the recorder holds every sample (then it closes)
    # plant/1/state: agent 1's relayed states are corroborated against its plant's own measurements
    assert set(a2.subscribe) == {"tether/trio/plant/2/state", "tether/trio/agent/1/state", "tether/trio/plant/1/state",
                                 "tether/trio/control/0/start", "tether/trio/control/0/recorded",
                                 "tether/trio/control/0/safety"}
    assert set(a2.sees) == {"@tether/trio/plant/2", "@tether/trio/agent/1"}
    assert a2.tokens == ("@tether/trio/agent/2",)
    assert set(g["agent-1"].subscribe) >= {"tether/trio/leader/4/state", "tether/trio/agent/3/state"}
    assert g["plant-3"].publish == ("tether/trio/plant/3/state",)
    assert set(g["plant-3"].subscribe) == {"tether/trio/agent/3/cmd", "tether/trio/control/0/start",
                                           "tether/trio/control/0/recorded", "tether/trio/control/0/safety"}
    # no agent or plant may publish outside its own keys
    for name, grant in g.items():
        role, _, nid = name.partition("-")
        if role in ("agent", "plant"):
            assert all(k.startswith(f"tether/trio/{role}/{nid}/") for k in grant.publish), name
            assert grant.tokens == (f"@tether/trio/{role}/{nid}",)


def test_collision_avoidance_lets_each_agent_hear_every_other_vehicle_and_nothing_more() -> None:
    """``[safety.avoid]``: the agent process subscribes to every other agent's state (``agent/node.py``);
    without those keys in its grant the authenticated run stalled at tick 0. Without avoidance the
    grant stays the in-neighbours'."""
    from tether.catalog import builtin_path

    m = ms.load(builtin_path("swap"))
    assert m.safety.avoid is not None
    for aid in m.agent_ids:
        g = {x.name: x for x in acl.grants(m, "sw")}[f"agent-{aid}"]
        # every key the agent declares (agent/node.py) is included by a granted expression, as Zenoh checks
        # (one wildcard for every vehicle: the rules grow as N, not N^2)
        declared = {f"tether/sw/agent/{j}/state" for j in m.agent_ids if j != aid}
        assert all(any(zenoh.KeyExpr(x).includes(zenoh.KeyExpr(d)) for x in g.subscribe) for d in declared), g
        assert "tether/sw/agent/*/state" in g.subscribe
        ins = {f"tether/sw/plant/{j}/state" for j, _ in ms.in_neighbours(m, aid) if j != m.leader.id}
        assert not any(k.endswith("/cmd") or "/plant/" in k and k != f"tether/sw/plant/{aid}/state" and k not in ins
                       for k in g.subscribe), g.subscribe
    bare = msgspec.structs.replace(m, safety=msgspec.structs.replace(m.safety, avoid=None))
    g = {x.name: x for x in acl.grants(bare, "sw")}["agent-1"]
    assert not [k for k in g.subscribe if k.startswith("tether/sw/agent/")], g.subscribe  # hears the leader only


def test_units_run_the_entry_points_with_arguments_they_accept(deployment: gen.Deployment) -> None:
    from deploy import router as router_cli
    from deploy import start as start_cli
    from cli import main as cli

    units = sorted(deployment.out.glob("hosts/*/systemd/*.service"))
    assert len(units) == 10
    for u in units:
        text = u.read_text()
        assert not gen._PLACEHOLDER.search(text), u  # every placeholder filled
        argv = shlex.split(next(line for line in text.splitlines() if line.startswith("ExecStart=")).partition("=")[2])
        if argv[0] == PYTHON_ON_HOSTS:
            parser = {"deploy.router": router_cli, "deploy.start": start_cli}[argv[2]].build_parser()
            args = parser.parse_args(argv[3:])
        else:
            assert argv[0] == TETHER_ON_HOSTS
            args = cli.build_parser().parse_args(argv[1:])
            assert args.clock == "realtime" and args.ns == "trio"
        assert Path(getattr(args, "zenoh_config", None) or args.config).is_file(), u
        # the control loop at a real-time priority, set by systemd at exec; the recorder and the start tool not
        control = u.name.startswith(("tether-agent", "tether-plant", "tether-leader", "tether-router"))
        assert ("CPUSchedulingPolicy=rr" in text and "CPUSchedulingPriority=10" in text) == control, u


# --------------------------------------------------------------------------- mTLS
@pytest.mark.slow  # deploy security: a real mTLS router and clients
def test_a_generated_client_profile_links_to_the_router_with_mtls(deployment: gen.Deployment, router: str) -> None:
    with open_as(deployment, "plant-3") as plant3, open_as(deployment, "agent-3") as agent3:
        assert [str(z) for z in agent3.info.routers_zid()] == [router]
        inbox = Inbox()
        plant3.declare_subscriber(KEYS.topic("agent", 3, "cmd"), inbox.put)
        pub = agent3.declare_publisher(KEYS.topic("agent", 3, "cmd"))
        wait_matching(pub)
        pub.put(cmd(3, [0.5, -0.5]))
        inbox.wait_for(cmd(3, [0.5, -0.5]))


@pytest.mark.slow  # deploy security: a real mTLS router and clients
def test_no_link_without_a_certificate_of_the_deployment_ca(deployment: gen.Deployment, router: str,
                                                            tmp_path: Path) -> None:
    tls = deployment.host_dir("agent-3") / "tls"
    endpoint = deployment.plan.router.dial
    assert endpoint is not None
    other = pki.make_ca(tmp_path / "other", "another CA", 1)
    fake_crt, fake_key = pki.issue(other, tmp_path / "other", "agent-3", "agent-3.trio", ["127.0.0.1"], 1)
    attempts = {
        "no client certificate": tp.TlsFiles(root_ca_certificate=str(tls / "ca.crt")),
        "agent 3's name, another CA": tp.TlsFiles(root_ca_certificate=str(tls / "ca.crt"), enable_mtls=True,
                                                  connect_certificate=str(fake_crt), connect_private_key=str(fake_key)),
        "the CA's certificate as its own": tp.TlsFiles(root_ca_certificate=str(tls / "ca.crt"), enable_mtls=True,
                                                       connect_certificate=str(deployment.ca.cert),
                                                       connect_private_key=str(deployment.ca.key)),
    }
    for what, files in attempts.items():
        with pytest.raises(tp.TransportError, match="Unable to connect"):
            with tp.open_session(tp.ZenohSettings(mode="client", connect=(endpoint,), tls=files)):
                pytest.fail(f"{what}: a link was opened")
    # counter-check: the same settings with agent 3's real certificate do link
    real = tp.TlsFiles(root_ca_certificate=str(tls / "ca.crt"), enable_mtls=True,
                       connect_certificate=str(tls / "agent-3.crt"), connect_private_key=str(tls / "agent-3.key"))
    with tp.open_session(tp.ZenohSettings(mode="client", connect=(endpoint,), tls=real)) as s:
        assert [str(z) for z in s.info.routers_zid()] == [router]


@pytest.mark.slow  # deploy security: a real mTLS router and clients
def test_plain_tcp_is_refused(deployment: gen.Deployment, router: str) -> None:
    endpoint = deployment.plan.router.dial
    assert endpoint is not None and endpoint.startswith("tls/")
    with pytest.raises(tp.TransportError, match="Unable to connect"):
        with tp.open_session(tp.ZenohSettings(mode="client", connect=("tcp/" + endpoint.removeprefix("tls/"),))):
            pytest.fail("a plain TCP session linked to the router")
    # a generated profile cannot be talked into plain TCP either, even towards a TCP router: its link
    # protocols are TLS only (counter-check: with TCP allowed, the same profile links)
    plain = tp.loopback_endpoint(tp.free_tcp_port())
    with tp.open_session(tp.ZenohSettings(mode="router", listen=(plain,), scouting_delay=0.0)):
        to_plain = {"connect__endpoints": [plain], "connect__timeout_ms": 0}
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            with open_as(deployment, "agent-3", **to_plain):
                pytest.fail("a generated profile opened a TCP link")
        with open_as(deployment, "agent-3", transport__link__protocols=["tls", "tcp"], **to_plain) as s:
            assert len(list(s.info.routers_zid())) == 1


# --------------------------------------------------------------------------- access control
def attack(dep: gen.Deployment, overhear: frozenset[bytes] = frozenset(),
           **json5: object) -> tuple[list[bytes], list[bytes], list[bytes], list[tuple[str, bool]]]:
    """Agent 2's identity tries to command agent 3's plant, fake agent 3's state, eavesdrop on agent 3's
    commands and fake plant 3's token, while agent 3 and plant 3 do their legitimate work. Returns
    what plant 3 received on agent 3's cmd, what agent 1 received on agent 3's state, what the
    attacker's subscriber on the whole namespace got, and the tokens agent 3 saw before plant 3's
    real one. ``overhear``: payloads to wait for on the attacker's own subscriber before returning
    (where the attack is expected to succeed: it is then the condition the caller asserts).
    ``json5`` replaces keys in every profile (e.g. the router to use)."""
    evil_cmd, evil_state = cmd(3, [9.9, 9.9]), wire.encode(wire.State(sender=3, seq=0, k=0, t=0.0, p=[9.9, 9.9],
                                                                     vel=[0.0, 0.0], a=[0.0, 0.0]))
    with open_as(dep, "plant-3", **json5) as plant3, open_as(dep, "agent-1", **json5) as agent1, \
            open_as(dep, "agent-3", **json5) as agent3, open_as(dep, "agent-2", **json5) as evil:
        cmds, states, overheard, fence = Inbox(), Inbox(), Inbox(), Inbox()
        plant3.declare_subscriber(KEYS.topic("agent", 3, "cmd"), cmds.put)
        agent1.declare_subscriber(KEYS.topic("agent", 3, "state"), states.put)
        agent3.declare_subscriber(KEYS.topic("agent", 2, "state"), fence.put)
        seen = Tokens()
        agent3.liveliness().declare_subscriber(KEYS.tokens, seen.put, history=True)
        good_cmd = agent3.declare_publisher(KEYS.topic("agent", 3, "cmd"))
        good_state = agent3.declare_publisher(KEYS.topic("agent", 3, "state"))
        bad_cmd = evil.declare_publisher(KEYS.topic("agent", 3, "cmd"))
        bad_state = evil.declare_publisher(KEYS.topic("agent", 3, "state"))
        own_state = evil.declare_publisher(KEYS.topic("agent", 2, "state"))
        for pub in (good_cmd, good_state, bad_cmd, bad_state, own_state):
            wait_matching(pub)  # the attacker's puts are really sent, not filtered at its side
        # eavesdrop on the whole namespace (declared after the matching, which it would satisfy locally;
        # the fences below come after it on the attacker's link)
        evil.declare_subscriber(KEYS.everything, overheard.put)
        fake_token = evil.liveliness().declare_token(KEYS.token("plant", 3))
        own_token = evil.liveliness().declare_token(KEYS.token("agent", 2))
        for rnd in range(2):  # two rounds: the first round's attack has had a round trip to arrive
            for _ in range(10):
                bad_cmd.put(evil_cmd)
                bad_state.put(evil_state)
            own_state.put(f"fence {rnd}".encode())  # on the attacker's link, after its attack
            fence.wait_for(f"fence {rnd}".encode())
            good_cmd.put(cmd(3, [0.0, float(rnd)]))
            good_state.put(f"state {rnd}".encode())
            cmds.wait_for(cmd(3, [0.0, float(rnd)]))
            states.wait_for(f"state {rnd}".encode())
        seen.wait_for(KEYS.token("agent", 2))  # declared after the fake token, on the same link
        tokens_before = list(seen.events)
        real_token = plant3.liveliness().declare_token(KEYS.token("plant", 3))
        seen.wait_for(KEYS.token("plant", 3))  # the watcher does see plant 3's real token
        for payload in overhear:  # the router forwards to the attacker on its own link, maybe later
            overheard.wait_for(payload)
        del fake_token, own_token, real_token
        return cmds.items, states.items, overheard.items, tokens_before


@pytest.mark.slow  # deploy security: a real mTLS router and clients
def test_agent_2_cannot_move_agent_3_through_the_router(deployment: gen.Deployment, router: str,
                                                        tmp_path: Path) -> None:
    evil = cmd(3, [9.9, 9.9])
    cmds, states, overheard, tokens = attack(deployment)
    assert evil not in cmds and [c for c in cmds if c != evil] == [cmd(3, [0.0, 0.0]), cmd(3, [0.0, 1.0])]
    assert states == [b"state 0", b"state 1"]
    legit = {cmd(3, [0.0, 0.0]), cmd(3, [0.0, 1.0]), b"state 0", b"state 1"}
    assert not legit & set(overheard)  # it got only its own puts, delivered inside its own session
    assert {key for key, _ in tokens} == {KEYS.token("agent", 2)}  # agent 3 is told of its neighbours only

    # counter-check: the same attack through a router with the same profile but no access control
    # succeeds, so the assertions above do test the access control
    port = tp.free_tcp_port()
    open_router = config_of(deployment, "router", access_control__enabled=False,
                            listen__endpoints=[f"tls/127.0.0.1:{port}"])
    with zenoh.open(open_router):
        cmds, states, overheard, tokens = attack(deployment, overhear=frozenset(legit),
                                                 connect__endpoints=[f"tls/127.0.0.1:{port}"])
    assert evil in cmds and legit <= set(overheard) and any(s not in (b"state 0", b"state 1") for s in states)
    assert (KEYS.token("plant", 3), True) in tokens


def order(action: str, reason: str) -> bytes:
    return wire.encode(wire.SafetyCommand(sender=0, seq=0, k=0, t=0.0, action=action, reason=reason))


def order_attack(dep: gen.Deployment, **json5: object) -> tuple[list[bytes], list[bytes]]:
    """Agent 2's identity publishes land and e-stop orders on the control key, then the operator
    (``control-0``) publishes its own; returns what plant 3 and agent 1 received there."""
    forged = [order("estop", "agent 2 says so"), order("land", "agent 2 says so")]
    with open_as(dep, "plant-3", **json5) as plant3, open_as(dep, "agent-1", **json5) as agent1, \
            open_as(dep, "agent-3", **json5) as agent3, open_as(dep, "agent-2", **json5) as evil, \
            open_as(dep, "control-0", **json5) as operator:
        at_plant, at_agent, fence = Inbox(), Inbox(), Inbox()
        plant3.declare_subscriber(KEYS.safety, at_plant.put)
        agent1.declare_subscriber(KEYS.safety, at_agent.put)
        agent3.declare_subscriber(KEYS.topic("agent", 2, "state"), fence.put)
        bad = evil.declare_publisher(KEYS.safety)
        own_state = evil.declare_publisher(KEYS.topic("agent", 2, "state"))
        good = operator.declare_publisher(KEYS.safety)
        for pub in (bad, own_state, good):
            wait_matching(pub)
        for rnd in range(2):
            for payload in forged * 5:
                bad.put(payload)
            own_state.put(f"fence {rnd}".encode())  # on the attacker's link, after its orders
            fence.wait_for(f"fence {rnd}".encode())
            good.put(order("land", f"operator {rnd}"))
            at_plant.wait_for(order("land", f"operator {rnd}"))
            at_agent.wait_for(order("land", f"operator {rnd}"))
        return at_plant.items, at_agent.items


@pytest.mark.slow  # deploy security: a real mTLS router and clients
def test_only_the_operator_can_order_a_land_or_an_estop(deployment: gen.Deployment, router: str) -> None:
    legit = [order("land", "operator 0"), order("land", "operator 1")]
    at_plant, at_agent = order_attack(deployment)
    assert at_plant == legit and at_agent == legit
    g = {x.name: x for x in acl.grants(ms.load(deployment.host_dir("agent-1") / "mission.toml"), "trio")}
    assert [name for name, grant in g.items() if KEYS.safety in grant.publish] == ["control-0"]
    assert all(KEYS.safety in grant.subscribe for name, grant in g.items() if name.startswith(("agent-", "plant-")))

    # counter-check: through a router with the same profile but no access control, the forged orders arrive
    port = tp.free_tcp_port()
    open_router = config_of(deployment, "router", access_control__enabled=False,
                            listen__endpoints=[f"tls/127.0.0.1:{port}"])
    with zenoh.open(open_router):
        at_plant, at_agent = order_attack(deployment, connect__endpoints=[f"tls/127.0.0.1:{port}"])
    assert order("estop", "agent 2 says so") in at_plant and order("land", "agent 2 says so") in at_agent


def reply_attack(dep: gen.Deployment, **json5: object) -> list[tuple[str, bytes]]:
    """The operator (``control-0``) asks ``agent/*/netem``, as ``tether netem-set`` does; agent 3
    answers for itself, and agent 2 answers first in agent 3's name (a reply keyed
    ``agent/3/netem``), then for itself. Returns the (key, payload) replies the operator got, once
    both real answers are in (agent 2's own answer leaves after its forged one, on the same link)."""
    forged, own2, own3 = b"agent 3 (forged by agent 2)", b"agent 2", b"agent 3"
    with open_as(dep, "control-0", **json5) as operator, open_as(dep, "agent-3", **json5) as agent3, \
            open_as(dep, "agent-2", **json5) as evil:
        def answer3(query: zenoh.Query) -> None:
            query.reply(KEYS.topic("agent", 3, "netem"), own3)

        def answer2(query: zenoh.Query) -> None:
            query.reply(KEYS.topic("agent", 3, "netem"), forged)
            query.reply(KEYS.topic("agent", 2, "netem"), own2)

        q3 = agent3.declare_queryable(KEYS.topic("agent", 3, "netem"), answer3)
        q2 = evil.declare_queryable(KEYS.topic("agent", 2, "netem"), answer2)
        got: list[tuple[str, bytes]] = []
        deadline = time.monotonic() + WAIT
        while not {own2, own3} <= {p for _, p in got}:  # until both queryables are known and answered
            assert time.monotonic() < deadline, f"the agents' answers did not arrive within {WAIT} s (got {got})"
            # every reply, not one per key (the default consolidation would hide a second reply on agent/3/netem)
            for reply in operator.get("tether/trio/agent/*/netem", timeout=1.0,
                                      consolidation=zenoh.ConsolidationMode.NONE):
                if reply.ok is not None:
                    got.append((str(reply.ok.key_expr), reply.ok.payload.to_bytes()))
        del q2, q3
        return got


def test_an_agent_can_answer_the_operators_query_only_for_itself(deployment: gen.Deployment, router: str) -> None:
    forged = (KEYS.topic("agent", 3, "netem"), b"agent 3 (forged by agent 2)")
    got = reply_attack(deployment)
    assert forged not in got
    assert {(KEYS.topic("agent", 2, "netem"), b"agent 2"), (KEYS.topic("agent", 3, "netem"), b"agent 3")} <= set(got)
    g = {x.name: x for x in acl.grants(ms.load(deployment.host_dir("agent-1") / "mission.toml"), "trio")}
    assert all(grant.replies == (KEYS.topic("agent", int(name[6:]), "netem"), KEYS.topic("agent", int(name[6:]), "lastplant"))
               for name, grant in g.items() if name.startswith("agent-"))

    # counter-check: through a router with the same profile but no access control, the forged reply arrives
    port = tp.free_tcp_port()
    open_router = config_of(deployment, "router", access_control__enabled=False,
                            listen__endpoints=[f"tls/127.0.0.1:{port}"])
    with zenoh.open(open_router):
        assert forged in reply_attack(deployment, connect__endpoints=[f"tls/127.0.0.1:{port}"])


@pytest.fixture(scope="module")
def peer_deployment(tmp_path_factory: pytest.TempPathFactory, mission_file: Path,
                    deployment: gen.Deployment) -> gen.Deployment:
    """A peer deployment on loopback (every process listens on its own port), signed by the same CA."""
    root = tmp_path_factory.mktemp("peer")
    out = root / "out"
    body = "network = \"peer\"\n"
    for table in ("router", "leader", "recorder"):
        body += f"[{table}]\naddress = \"127.0.0.1\"\nport = {tp.free_tcp_port()}\n"
    body += f"out = {toml_str(root / 'runs')}\n"  # in [recorder]
    for aid in (1, 2, 3):  # the agent listens on port, its plant on port + 1
        body += f"[[agents]]\nid = {aid}\naddress = \"127.0.0.1\"\nport = {tp.free_tcp_port(span=2)}\n"
    return gen.generate(mission_file, out, hosts=write_hosts(root / "hosts.toml", out, body), ca=deployment.out / "ca")


@pytest.mark.slow  # deploy security: a real mTLS router and clients
def test_a_listening_peer_enforces_the_acl_on_direct_links(peer_deployment: gen.Deployment) -> None:
    """Peer network: agent 2's identity dials plant 3 directly (no router on the path); plant 3's own
    access control drops its command, and takes agent 3's."""
    dep = peer_deployment
    plant = next(p for p in dep.plan.placements if p.name == "plant-3")
    assert plant.mode == "peer" and plant.listen is not None
    direct = {"connect__endpoints": [plant.dial], "listen__endpoints": [], "scouting__gossip__enabled": False}

    def run(acl_on: bool) -> list[bytes]:
        got = Inbox()
        with open_as(dep, "plant-3", connect__endpoints=[], access_control__enabled=acl_on) as plant3, \
                open_as(dep, "agent-2", **direct) as evil, open_as(dep, "agent-3", **direct) as agent3:
            assert str(plant3.info.zid()) in {str(z) for z in evil.info.peers_zid()}  # a direct link
            plant3.declare_subscriber(KEYS.topic("agent", 3, "cmd"), got.put)
            bad = evil.declare_publisher(KEYS.topic("agent", 3, "cmd"))
            good = agent3.declare_publisher(KEYS.topic("agent", 3, "cmd"))
            wait_matching(bad)
            wait_matching(good)
            for rnd in range(2):
                for _ in range(10):
                    bad.put(cmd(3, [9.9, 9.9]))
                good.put(cmd(3, [0.0, float(rnd)]))
                got.wait_for(cmd(3, [0.0, float(rnd)]))
        return got.items

    assert cmd(3, [9.9, 9.9]) not in run(acl_on=True)
    assert cmd(3, [9.9, 9.9]) in run(acl_on=False)  # counter-check: the peer's ACL is what stops it


# --------------------------------------------------------------------------- rotation
@pytest.mark.slow  # deploy security: a real mTLS router and clients
def test_rotated_certificates_from_the_same_ca_link_without_restarting_the_router(
        deployment: gen.Deployment, router: str, mission_file: Path, client_hosts: str, tmp_path: Path) -> None:
    out2 = tmp_path / "rotated"
    dep2 = gen.generate(mission_file, out2, hosts=write_hosts(tmp_path / "hosts.toml", out2, client_hosts),
                        ca=deployment.out / "ca")
    new_crt = dep2.host_dir("agent-3") / "tls" / "agent-3.crt"
    old_crt = deployment.host_dir("agent-3") / "tls" / "agent-3.crt"
    assert new_crt.read_bytes() != old_crt.read_bytes()
    assert (dep2.out / "ca" / "ca.crt").read_bytes() == deployment.ca.cert.read_bytes()
    with zenoh.open(config_of(dep2, "agent-3")) as s:
        assert [str(z) for z in s.info.routers_zid()] == [router]


# --------------------------------------------------------------------------- a real run
Procs = list[tuple[str, subprocess.Popen]]


def failures(procs: Procs, logs: Path) -> str:
    """The processes that ended badly, with the end of their logs ('' if none)."""
    return "\n".join(f"{n} (exit {p.poll()}):\n{(logs / f'{n}.log').read_text()[-3000:]}"
                     for n, p in procs if p.poll() not in (None, 0))


async def ask_agents(dep: gen.Deployment, procs: Procs, logs: Path) -> list[control.Answer]:
    """As ``control-0``: wait until every process is up (failing at once if one ends badly), then
    ``tether netem-set`` every agent's in-links to the ideal profile."""
    settings = tp.ZenohSettings(config_file=str(dep.config("control-0")))
    m = ms.load(dep.host_dir("leader") / "mission.toml")
    async with tp.open_session(settings) as session:
        up = asyncio.create_task(tp.wait_for_tokens(session, [KEYS.token(r, i) for r, i in start_cmd.members(m)], 60.0))
        while not up.done():
            if failed := failures(procs, logs):
                up.cancel()
                raise AssertionError(failed)
            await asyncio.wait({up}, timeout=0.1)
        up.result()
    return await control.netem_set(settings, "trio", control.rule_of("ideal", None, None), None, timeout=WAIT)


@pytest.fixture(params=["client", "peer"])
def running(request: pytest.FixtureRequest) -> Iterator[gen.Deployment]:
    """A deployment of either network with its router running."""
    if request.param == "client":
        request.getfixturevalue("router")
        yield request.getfixturevalue("deployment")
        return
    dep: gen.Deployment = request.getfixturevalue("peer_deployment")
    proc, _ = start_router(dep.config("router"), dep.out / "router.log")
    try:
        yield dep
    finally:
        assert stop(proc) == 0, (dep.out / "router.log").read_text()


@pytest.mark.slow  # every process of the deployment, in real time
def test_a_real_time_run_over_the_generated_deployment(running: gen.Deployment) -> None:
    """Every role started from its unit's ExecStart line (tether and the router's Python replaced by
    this interpreter), mTLS and access control on: the run ends well, the agents' netem-set control
    passes, samples flow on every edge, no link is silent. This is what shows that the grants are
    enough, in a star of clients and in a mesh of peers around the router."""
    deployment = running
    procs: Procs = []
    logs = deployment.out / "logs"
    logs.mkdir(exist_ok=True)
    start_line = None
    try:
        for u in sorted(deployment.out.glob("hosts/*/systemd/*.service")):
            argv = shlex.split(next(x for x in u.read_text().splitlines() if x.startswith("ExecStart="))[10:])
            if argv[0] == TETHER_ON_HOSTS:
                argv = [sys.executable, "-m", "cli", *argv[1:]]
            elif argv[2] == "deploy.router":
                continue  # running already
            else:
                argv = [sys.executable, *argv[1:]]
            if u.name == "tether-start.service":
                start_line = [*argv, "--lead", "1.0", "--timeout", "60"]
                continue
            with open(logs / f"{u.stem}.log", "wb") as fh:
                procs.append((u.stem, subprocess.Popen(argv, cwd=REPO, stdin=subprocess.DEVNULL, stdout=fh,
                                                       stderr=subprocess.STDOUT)))
        assert start_line is not None and len(procs) == 8
        # before the start: the control identity changes the agents' emulated links (tether netem-set's
        # queries and the agents' replies pass the access control)
        answers = asyncio.run(ask_agents(deployment, procs, logs))
        assert sorted((a.node, a.error) for a in answers) == [(1, None), (2, None), (3, None)]
        assert sorted((c["src"], c["dst"]) for a in answers for c in a.changed) == [(1, 2), (2, 3), (3, 1), (4, 1)]
        with open(logs / "start.log", "wb") as fh:
            starter = subprocess.Popen(start_line, cwd=REPO, stdin=subprocess.DEVNULL, stdout=fh,
                                       stderr=subprocess.STDOUT)
        procs.append(("start", starter))
        deadline = time.monotonic() + 90.0
        while any(p.poll() is None for _, p in procs):  # every process ends by itself after the run
            assert not (failed := failures(procs, logs)), failed
            assert time.monotonic() < deadline, "the run did not end within 90 s"
            time.sleep(0.1)
    finally:
        for _, p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    out = Path(deployment.plan.hosts.recorder.out)  # type: ignore[union-attr]
    run = np.load(out / "run.npz", allow_pickle=True)
    meta = json.loads(str(run["meta"]))
    # real time with DROP streams on a shared 2-core machine: most samples, as for the local launcher
    # (tests/test_runtime.py); losses seen here were the last tick's telemetry, cut by the end of the run,
    # and now and then one state sample
    assert meta["samples_expected"] == 3 * 21 * 2 + 21
    assert meta["samples_recorded"] >= 0.9 * meta["samples_expected"], (
        meta, (logs / "tether-recorder-0.log").read_text()[-2000:])
    # every edge (agent 1 hears the leader and agent 3, agent 2 hears 1, agent 3 hears 2) delivered, and
    # no neighbour went silent (link_src pads the agents with fewer in-links with 0)
    edges = run["link_src"] > 0
    assert sorted(run["link_src"][edges].tolist()) == [1, 2, 3, 4]
    assert np.nansum(run["link_silent"][:, edges]) == 0
    assert (np.nanmax(run["link_received"][:, edges], axis=0) >= 0.9 * 21).all()


# --------------------------------------------------------------------------- bad input
def test_transport_config_file_conflicts_and_errors_name_the_field(tmp_path: Path) -> None:
    with pytest.raises(tp.SettingsError, match="config_file: is given together with mode, connect"):
        tp.zenoh_config(tp.ZenohSettings(config_file="x.json5", mode="client", connect=("tcp/127.0.0.1:1",)))
    with pytest.raises(tp.SettingsError, match="config_file: .*No such file"):
        tp.zenoh_config(tp.ZenohSettings(config_file=str(tmp_path / "missing.json5")))
    bad = tmp_path / "bad.json5"
    bad.write_text('{mode: "client", trasport: {}}')
    with pytest.raises(tp.SettingsError, match="unknown field `trasport`"):
        tp.zenoh_config(tp.ZenohSettings(config_file=str(bad)))


M = ms.loads(MISSION)

BAD_HOSTS = [
    ('[router]\nadress = "10.0.0.1"\n', "router.adress", "rename it to `address`"),
    ('[[agents]]\nid = 1\naddress = "10.0.0.11"\n[[agents]]\nid = 2\naddress = "10.0.0.12"\n',
     "agents", "lacks agent 3"),
    ('[[agents]]\nid = 1\naddress = "a1"\n[[agents]]\nid = 2\naddress = "a2"\n[[agents]]\nid = 3\naddress = "a3"\n'
     '[[agents]]\nid = 7\naddress = "a7"\n', "agent 7.id", "not an agent of mission 'trio'; use one of [1, 2, 3]"),
    ('[[agents]]\nid = 1\naddress = "a1"\n[[agents]]\nid = 1\naddress = "a2"\n[[agents]]\nid = 2\naddress = "a2"\n'
     '[[agents]]\nid = 3\naddress = "a3"\n', "agent 1 (2nd [[agents]]).id", "listed twice"),
    ('[router]\naddress = "tls/10.0.0.1:7447"\n', "router.address", "no scheme, no port"),
    ('[router]\naddress = "10.0.0.1"\nport = 70000\n', "router.port", "1 to 65535"),
    ('network = "mesh"\n', "network", 'use "client" or "peer"'),
    ('network = "peer"\n[router]\naddress = "10.0.0.1"\n[leader]\naddress = "10.0.0.1"\n', "leader.port",
     "listens on tls/10.0.0.1:7447 like router"),
    ('lease = 0.0\n', "lease", "must be > 0"),
    ('config_dir = "etc/tether"\n', "config_dir", "absolute path"),
    ('[router]\naddress = 10\n', "router.address", "is an integer but must be a string"),
    ('port = "7447"\n', "port", "must be an integer; write e.g. `port = 7447` (no quotes)"),
]


@pytest.mark.parametrize(("body", "field", "fix"), BAD_HOSTS, ids=[b[1] + ":" + b[2][:20] for b in BAD_HOSTS])
def test_bad_hosts_files_name_the_field_and_the_fix(body: str, field: str, fix: str) -> None:
    with pytest.raises(hosts.HostsError) as err:
        hosts.plan(M, hosts.loads("version = 1\n" + body, "h.toml"), "h.toml")
    problems = dict(err.value.problems)
    assert field in problems, err.value
    assert fix.lower() in problems[field].lower(), err.value
    assert str(err.value).startswith("h.toml: ")


def test_a_hosts_file_without_version_is_refused() -> None:
    with pytest.raises(hosts.HostsError, match=r"version: is missing; add `version = 1`"):
        hosts.loads('[router]\naddress = "10.0.0.1"\n')


def test_generator_errors_exit_2_naming_the_problem(tmp_path: Path, mission_file: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    bad_mission = tmp_path / "bad.toml"
    bad_mission.write_text(MISSION.replace("rate = 20.0", "rate = -20.0"))
    assert gen.main([str(bad_mission), "--out", str(tmp_path / "o1")]) == 2
    assert "rate: is -20.0 Hz" in capsys.readouterr().err
    hosts_file = tmp_path / "hosts.toml"
    hosts_file.write_text('version = 1\n[leader]\naddres = "x"\n')
    assert gen.main([str(mission_file), "--out", str(tmp_path / "o2"), "--hosts", str(hosts_file)]) == 2
    assert "leader.addres: is not a known field; rename it to `address`" in capsys.readouterr().err
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    assert gen.main([str(mission_file), "--out", str(tmp_path / "full")]) == 2
    assert "is not empty; give a new directory, or --force" in capsys.readouterr().err
    assert gen.main([str(mission_file), "--out", str(tmp_path / "o3"), "--ca", str(tmp_path / "noca")]) == 2
    assert "ca.crt is missing" in capsys.readouterr().err
    (tmp_path / "old" / "ca").mkdir(parents=True)
    (tmp_path / "old" / "ca" / "ca.key").write_text("")
    assert gen.main([str(mission_file), "--out", str(tmp_path / "old"), "--force"]) == 2
    assert "already holds a CA" in capsys.readouterr().err
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    assert gen.main([str(mission_file), "--out", str(shared / "o4")]) == 2  # others could rename o4 and put theirs
    assert "--out: " in (err := capsys.readouterr().err) and "no sticky bit" in err, err
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists() and not (shared / "o4").exists()


def test_generated_keys_are_private_and_every_file_is_the_users_own(deployment: gen.Deployment) -> None:
    """Keys mode 0600 in mode-0700 directories (``ca/``, each host's ``tls/``); every other file a
    plain file of this user with one name, not writable by others; no temporary name left."""
    import os
    import stat

    out = deployment.out
    private = [out / "ca", *sorted((out / "hosts").glob("*/tls"))]
    assert len(private) == 1 + len(deployment.plan.host_names)
    for d in private:
        st = os.lstat(d)
        assert stat.S_ISDIR(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o700 and st.st_uid == os.geteuid(), d
    files = [*(f for written in deployment.files.values() for f in written),
             *(out / name for name in ("acl.json5", "DEPLOY.md", "ca/ca.crt", "ca/ca.key"))]
    assert len(files) > 4 and not list(out.rglob(".*")), "a temporary name was left behind"
    for f in files:
        st = os.lstat(f)
        assert stat.S_ISREG(st.st_mode) and st.st_nlink == 1 and st.st_uid == os.geteuid(), f
        want = 0o600 if f.suffix == ".key" else 0o644
        assert stat.S_IMODE(st.st_mode) == want, f"{f}: {stat.S_IMODE(st.st_mode):04o}"
