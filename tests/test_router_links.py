"""Least privilege between routers: a router-to-router link carries only what the processes on the
far side may publish and subscribe (``deploy/acl.py`` ``link_grant``, ``deploy/gen.py`` ``link_grants``).

* Fast: the generated grants of a two-site Section 4 (ground: leader, recorder, operator, agents 1
  and 2; field: agents 3 and 4) are, field by field, the union of the far side's process grants, and
  the field router's grant at the ground router holds none of the ground's keys.
* Real (a real ground router, ``python -m deploy.router`` with its generated configuration; a
  compromised field router, the real Zenoh router of the generated field configuration with its own
  access control switched off, as an attacker who holds its key would run it; real sessions of the
  deployment's identities on loopback): the field router's puts on the leader's state, the start and
  the e-stop never reach the ground's processes, while the legitimate traffic still flows both ways
  through the same link (agent 2's state to agent 3, plant 3's state to the recorder, the operator's
  order to both sites). Counter-check: with the namespace-wide grant routers held before (the
  peers' section, ``acl.json5``) the same forged messages arrive.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from deploy import acl, gen
from tests.support import free_port
from tests.test_deploy import Inbox, config_of, read_json5, start_router, stop, wait_matching
from tether import mission as ms
from tether import wire
from tether.catalog import builtin_path

SECTION4 = builtin_path("section4")
NS = "section4"
K = wire.Keys(NS)
GROUND = {"leader-5", "control-0", "recorder-0", "agent-1", "plant-1", "agent-2", "plant-2"}
FIELD = {"agent-3", "plant-3", "agent-4", "plant-4"}


def two_sites(tmp: Path) -> gen.Deployment:
    """Section 4 on two sites, every host on loopback, each router on a port of its own."""
    out = tmp / "deploy"
    text = f"""version = 1
config_dir = {json.dumps(str(out / "hosts" / "{host}"))}
[[routers]]
name = "ground"
address = "127.0.0.1"
port = {free_port()}
[[routers]]
name = "field"
address = "127.0.0.1"
port = {free_port()}
connect = ["ground"]
[leader]
address = "127.0.0.1"
[recorder]
address = "127.0.0.1"
out = {json.dumps(str(tmp / "runs"))}
""" + "".join(f'[[agents]]\nid = {i}\naddress = "127.0.0.1"\nrouter = "{"ground" if i < 3 else "field"}"\n'
              for i in (1, 2, 3, 4))
    (tmp / "hosts.toml").write_text(text)
    return gen.generate(SECTION4, out, hosts=tmp / "hosts.toml")


def access_of(dep: gen.Deployment, name: str) -> dict:
    return read_json5(dep.config(name))["access_control"]


def policy(access: dict, subject: str) -> dict[str, set[str]]:
    """What ``subject`` may do in an ``access_control`` section: ``(messages, flow)`` -> key expressions."""
    rules = {r["id"]: r for r in access["rules"]}
    (pol,) = [p for p in access["policies"] if subject in p["subjects"]]
    out: dict[str, set[str]] = {}
    for rid in pol["rules"]:
        r = rules[rid]
        for msg in r["messages"]:
            out.setdefault(f"{msg}:{r['flows'][0]}", set()).update(r["key_exprs"])
    return out


def test_a_router_link_is_granted_what_the_far_sides_processes_may_do(tmp_path: Path) -> None:
    dep = two_sites(tmp_path)
    m = ms.load(SECTION4)
    grants = {g.name: g for g in acl.grants(m, NS)}
    ground, field = access_of(dep, "router-ground"), access_of(dep, "router-field")
    for here, far, side in ((ground, "router-field", FIELD), (field, "router-ground", GROUND)):
        got = policy(here, far)
        for attr, key in (("publish", "put:ingress"), ("subscribe", "put:egress"), ("tokens", "liveliness_token:ingress"),
                          ("sees", "liveliness_token:egress"), ("serves", "declare_queryable:ingress")):
            want = {k for name in side for k in getattr(grants[name], attr)}
            assert got.get(key, set()) == want, (far, attr)
    published = policy(ground, "router-field")["put:ingress"]
    for key in (K.topic("leader", 5, "state"), K.start, K.safety, K.tick, K.topic("agent", 1, "state"),
                K.topic("plant", 2, "state")):
        assert key not in published  # the ground's keys: none may come in from the field
    assert K.everything not in published
    # a router's own processes keep their own grants there; a peer listener keeps the routers' relay grant
    assert policy(ground, "agent-3")["put:ingress"] == set(grants["agent-3"].publish)
    peers = read_json5(dep.out / "acl.json5")
    assert policy(peers, "router-field")["put:ingress"] == {K.everything}
    guide = (dep.out / "DEPLOY.md").read_text()
    assert "At `router-ground`, over its router-to-router links:" in guide


def test_one_router_keeps_the_single_section(tmp_path: Path) -> None:
    """One site: the router's configuration holds the section every listener holds (``acl.json5``)."""
    dep = gen.generate(SECTION4, tmp_path / "one")
    assert access_of(dep, "router") == read_json5(dep.out / "acl.json5")


def forge(dep: gen.Deployment, ground_endpoint: str) -> dict[str, list[bytes]]:
    """The compromised field router (its generated configuration, its own access control off, dialling
    ``ground_endpoint``) forges the leader's state, a start and an e-stop towards the ground, while the
    deployment's processes do their legitimate work through the same link. Returns what each ground
    and field subscriber received, once every legitimate message has arrived (the forged ones were
    sent first, on the same link)."""
    dial = {"connect__endpoints": [ground_endpoint]}
    leader_state = wire.encode(wire.State(sender=5, seq=0, k=0, t=0.0, p=[99.0, 99.0], vel=[0.0, 0.0], a=[0.0, 0.0]))
    start = b"forged start"
    estop = wire.encode(wire.SafetyCommand(sender=0, seq=0, k=0, t=0.0, action="estop", reason="the field router"))
    land = wire.encode(wire.SafetyCommand(sender=0, seq=0, k=0, t=0.0, action="land", reason="the operator"))
    with zenoh.open(config_of(dep, "router-field", access_control__enabled=False, **dial)) as evil, \
            zenoh.open(config_of(dep, "agent-1", **dial)) as agent1, \
            zenoh.open(config_of(dep, "plant-1", **dial)) as plant1, \
            zenoh.open(config_of(dep, "recorder-0", **dial)) as recorder, \
            zenoh.open(config_of(dep, "control-0", **dial)) as operator, \
            zenoh.open(config_of(dep, "agent-2", **dial)) as agent2, \
            zenoh.open(config_of(dep, "agent-3")) as agent3, zenoh.open(config_of(dep, "plant-3")) as plant3:
        got = {name: Inbox() for name in ("agent-1 leader", "plant-1 start", "plant-1 safety", "recorder start",
                                          "recorder plant-3", "agent-3 agent-2", "plant-3 safety")}
        agent1.declare_subscriber(K.topic("leader", 5, "state"), got["agent-1 leader"].put)
        plant1.declare_subscriber(K.start, got["plant-1 start"].put)
        plant1.declare_subscriber(K.safety, got["plant-1 safety"].put)
        recorder.declare_subscriber(K.start, got["recorder start"].put)
        recorder.declare_subscriber(K.topic("plant", 3, "state"), got["recorder plant-3"].put)
        agent3.declare_subscriber(K.topic("agent", 2, "state"), got["agent-3 agent-2"].put)
        plant3.declare_subscriber(K.safety, got["plant-3 safety"].put)
        forged = {evil.declare_publisher(K.topic("leader", 5, "state")): leader_state,
                  evil.declare_publisher(K.start): start, evil.declare_publisher(K.safety): estop}
        fence = evil.declare_publisher(K.topic("plant", 3, "state"))  # a key the field side may send on
        legit = {operator.declare_publisher(K.safety): land, agent2.declare_publisher(K.topic("agent", 2, "state")):
                 b"agent 2 state", plant3.declare_publisher(K.topic("plant", 3, "state")): b"plant 3 state"}
        for pub in [*forged, fence, *legit]:
            wait_matching(pub)  # every put below is really sent: a subscriber matched on the far side
        for rnd in range(2):
            for pub, payload in forged.items():
                for _ in range(5):
                    pub.put(payload)
            fence.put(f"fence {rnd}".encode())  # after the forgeries, on the same link
            got["recorder plant-3"].wait_for(f"fence {rnd}".encode())
            for pub, payload in legit.items():
                pub.put(payload)
            got["plant-1 safety"].wait_for(land)
            got["plant-3 safety"].wait_for(land)
            got["agent-3 agent-2"].wait_for(b"agent 2 state")
            got["recorder plant-3"].wait_for(b"plant 3 state")
        return {name: inbox.items for name, inbox in got.items()}


@pytest.mark.slow  # real routers and sessions with mTLS on loopback
def test_a_compromised_field_router_cannot_speak_for_the_ground(tmp_path: Path) -> None:
    dep = two_sites(tmp_path)
    endpoint = dep.plan.process("router-ground").dial
    assert endpoint is not None
    proc, _ = start_router(dep.config("router-ground"), tmp_path / "router-ground.log")
    try:
        got = forge(dep, endpoint)
    finally:
        assert stop(proc) == 0, (tmp_path / "router-ground.log").read_text()
    assert got["agent-1 leader"] == []  # the forged leader state never reached agent 1
    assert got["plant-1 start"] == [] and got["recorder start"] == []
    orders = [wire.decode(m) for m in got["plant-1 safety"]]
    assert orders and all(isinstance(o, wire.SafetyCommand) and o.action == "land" for o in orders), orders  # no e-stop
    assert got["agent-3 agent-2"] and got["plant-3 safety"] and b"plant 3 state" in got["recorder plant-3"]

    # counter-check: the ground router with the namespace-wide router grant (acl.json5, what every
    # router held before) lets the same forgeries in
    port = free_port()
    wide = read_json5(dep.out / "acl.json5")
    config = config_of(dep, "router-ground", listen__endpoints=[f"tls/127.0.0.1:{port}"])
    config.insert_json5("access_control", json.dumps(wide))
    with zenoh.open(config):
        got = forge(dep, f"tls/127.0.0.1:{port}")
    assert got["agent-1 leader"] and got["plant-1 start"] and got["recorder start"]
    assert any(getattr(wire.decode(m), "action", None) == "estop" for m in got["plant-1 safety"])
