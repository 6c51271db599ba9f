"""Access-control rules from a mission: who may publish, subscribe and declare what. Pure.

Each process has an identity, the common name (CN) of its certificate (``agent-3.<ns>``). Its
:class:`Grant` lists exactly the keys the runtime's code uses for that role (``agent/node.py``,
``plant/node.py``, ``leader/node.py``, ``recorder/node.py``, ``tether/node.py``,
``deploy/start.py``); :func:`access_control` turns the grants into Zenoh 1.x's ``access_control``
section, which every listening node (the router; every peer in a peer network) enforces on each
link, by the CN of the certificate the other side presented:

* the operator's stop orders (``tether land``, ``tether estop``) are published by ``control-0``
  alone, on ``tether/<ns>/control/0/safety``, which every agent and plant may subscribe to;
  ``control-0`` may also hear what the recorder hears (``tether record``, ``tether top``);
* ``ingress`` rules say what a node may send: ``put`` (publish), ``declare_subscriber``,
  ``liveliness_token``, ``declare_liveliness_subscriber``, and for ``tether netem-set`` (run-time
  changes of the emulated network) the agents' ``declare_queryable`` and ``reply`` (a reply only on
  the agent's own key, even to a wildcard query), the control's
  ``query`` and ``liveliness_query``;
* ``egress`` rules say what it may be sent: ``put`` on the keys it may subscribe to,
  ``liveliness_token`` of the processes it watches, queries to the agents and their replies to the
  control, and the declarations of other nodes' subscribers and queryables (so that its publishers
  and queries learn where to go).

``default_permission`` is ``deny``: anything not listed (queries, deletes, any other key) is
dropped. Zenoh allows a declaration when a rule's key expression *includes* the declared one
(``nodes_including`` in zenoh's ``authorization.rs``), so wildcard subscriptions are granted with
the very expression the code declares.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from tether import mission as ms
from tether import wire



@dataclass(frozen=True)
class Grant:
    """What one identity may do. Every field is a tuple of key expressions."""

    name: str
    """Process name (``agent-3``); its CN is ``<name>.<ns>``."""
    publish: tuple[str, ...] = ()
    """Keys it may put on."""
    subscribe: tuple[str, ...] = ()
    """Key expressions it may subscribe to, and on which puts are forwarded to it."""
    tokens: tuple[str, ...] = ()
    """Liveliness tokens it may declare."""
    watch: tuple[str, ...] = ()
    """Liveliness key expressions it may subscribe to."""
    sees: tuple[str, ...] = ()
    """Liveliness tokens whose (dis)appearance it is told about."""
    serves: tuple[str, ...] = ()
    """Queryables it may declare; it receives queries on, and may reply on, ``answers``."""
    answers: tuple[str, ...] = ()
    """Query key expressions it receives (a query's key may be a wildcard)."""
    replies: tuple[str, ...] = ()
    """Keys it may reply on: its own queryables' keys only, so that no process can answer a
    wildcard query (``agent/*/netem``) in another's name."""
    asks: tuple[str, ...] = ()
    """Key expressions it may query (and receive replies on)."""
    lists: tuple[str, ...] = ()
    """Liveliness key expressions it may query (``liveliness().get``)."""


def common_name(name: str, ns: str) -> str:
    """Certificate CN of process ``name`` in namespace ``ns``: ``agent-3.section4``."""
    return f"{name}.{ns}"


def grants(m: ms.Mission, ns: str, routers: tuple[str, ...] = ("router",)) -> list[Grant]:
    """One grant per process of mission ``m`` in namespace ``ns``, plus the router and the control
    (start) command. Lists exactly what the runtime declares for each role, nothing more.

    The control key ``tether/<ns>/control/0/safety`` (``tether land``/``tether estop``) is the
    operator's alone: only ``control-0`` (on the leader host, the ground station) may publish on
    it; every agent (its safety supervisor) and every plant (its command watchdog) may subscribe.

    ``routers``: the router processes (``router``, or ``router-ground``, ``router-field`` for two
    sites); each may route everything in the namespace to a listening peer, which it relays the whole
    swarm's traffic to. On a router-to-router link a router holds :func:`link_grant` instead: what the
    processes on its side may do, no more."""
    k = wire.Keys(ns)
    lid = m.leader.id
    every_token = k.tokens  # @tether/<ns>/**: what Node.watch and wait_for_tokens subscribe to
    every_netem = f"tether/{ns}/agent/*/netem"  # what tether netem-set asks (netem/control.py)

    def state_of(j: int) -> str:
        return k.topic("leader" if j == lid else "agent", j, "state")

    def token_of(j: int) -> str:
        return k.token("leader" if j == lid else "agent", j)

    out = [
        Grant(r, publish=(k.everything,), subscribe=(k.everything,), tokens=(every_token,),
              watch=(every_token,), sees=(every_token,), serves=(k.everything,), answers=(k.everything,),
              replies=(k.everything,), asks=(k.everything,), lists=(every_token,)) for r in routers
    ]
    out += [
        # record: lockstep with the plants co-located in their agents, its states for the recorder
        Grant(f"leader-{lid}", publish=(k.topic("leader", lid, "state"), k.topic("leader", lid, "record")),
              subscribe=(k.start, k.tick, k.recorded), tokens=(k.token("leader", lid),)),
        # the operator also watches the swarm (tether record, tether top): it may hear every stream
        # the recorder hears, and publish none of them
        Grant("control-0", publish=(k.start, k.tick, k.recorded, k.safety),
              subscribe=(k.acks, k.start, k.topic("leader", lid, "state"), k.topic("leader", lid, "record"),
                         f"tether/{ns}/agent/*/telemetry",
                         f"tether/{ns}/agent/*/record", f"tether/{ns}/plant/*/state", k.topic("world", 0, "state")),
              watch=(every_token,), sees=(every_token,),
              asks=(every_netem,), lists=(k.token("agent", "*"),)),
        Grant("recorder-0", publish=(k.topic("recorder", 0, "ack"),),
              subscribe=(k.topic("leader", lid, "state"), k.topic("leader", lid, "record"),
                         f"tether/{ns}/agent/*/telemetry", f"tether/{ns}/agent/*/record", f"tether/{ns}/plant/*/state",
                         k.start),
              tokens=(k.token("recorder", 0),), watch=(every_token,), sees=(every_token,)),
    ]
    for aid in m.agent_ids:
        nbrs = [j for j, _ in ms.in_neighbours(m, aid)]  # the keys the agent subscribes to
        # collision avoidance's, besides the law's inputs: every other vehicle's state, granted as one
        # expression (agent/*/state includes each key the agent declares) so that the rules grow as N,
        # not N^2 (docs/deploy.md, Scale)
        near = ms.nearby_vehicles(m, aid)
        vehicles = (f"tether/{ns}/agent/*/state",) if near else ()
        out.append(Grant(
            f"agent-{aid}",
            # record: lockstep with the plant co-located in the agent (--colocate-plants)
            publish=tuple(k.topic("agent", aid, t) for t in ("state", "cmd", "telemetry", "record")),
            # its agent in-neighbours' plants' measurements: their relayed states are corroborated
            # against them (real time, agent/node.py)
            subscribe=(k.topic("plant", aid, "state"), *(state_of(j) for j in nbrs),
                       *(k.topic("plant", j, "state") for j in nbrs if j != lid),
                       *vehicles, k.start, k.recorded, k.safety),
            tokens=(k.token("agent", aid),),
            watch=(every_token,),
            sees=(k.token("plant", aid), *(token_of(j) for j in nbrs)),
            # Node.netem_control: run-time netem changes; plant/resume.py: its plant's last state
            serves=(k.topic("agent", aid, "netem"), k.topic("agent", aid, "lastplant")),
            answers=(k.topic("agent", aid, "netem"), every_netem, k.topic("agent", aid, "lastplant")),
            # its own keys only: never a reply keyed for another
            replies=(k.topic("agent", aid, "netem"), k.topic("agent", aid, "lastplant")),
        ))
        out.append(Grant(
            f"plant-{aid}",
            publish=(k.topic("plant", aid, "state"),),
            subscribe=(k.topic("agent", aid, "cmd"), k.start, k.recorded, k.safety),
            tokens=(k.token("plant", aid),),
            watch=(every_token,),
            sees=(k.token("agent", aid),),
            asks=(k.topic("agent", aid, "lastplant"),),  # a restarted plant's last state (plant/resume.py)
        ))
    return out


def link_grant(name: str, behind: list[Grant]) -> Grant:
    """The grant of router ``name`` on a router-to-router link: exactly what the processes ``behind``
    it (its side of the link) may do, field by field the union of their grants, so that a router's
    link carries nothing that none of its processes may say or hear. One definition of who may say
    what: the processes' grants. Pure."""
    def union(field: str) -> tuple[str, ...]:
        return tuple(dict.fromkeys(k for g in behind for k in getattr(g, field)))

    return Grant(name, **{f.name: union(f.name) for f in fields(Grant) if f.name != "name"})


def access_control(gs: list[Grant], ns: str) -> dict[str, Any]:
    """Zenoh 1.x's ``access_control`` section for grants ``gs``: default deny, one subject per CN,
    one policy per subject. Rules with nothing to allow are left out (Zenoh rejects empty lists)."""
    k = wire.Keys(ns)
    rules: list[dict[str, Any]] = [
        # every node may be told who subscribes to what in this namespace (its publishers need it to
        # send at all) and who watches which tokens; these declarations carry no data
        _rule("declarations-out", ["declare_subscriber", "declare_queryable"], "egress", [k.everything]),
        _rule("liveliness-interest-out", ["declare_liveliness_subscriber"], "egress", [k.tokens]),
    ]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for g in gs:
        cn = common_name(g.name, ns)
        mine = [
            _rule(f"{g.name}:publish", ["put"], "ingress", g.publish),
            _rule(f"{g.name}:subscribe", ["declare_subscriber"], "ingress", g.subscribe),
            _rule(f"{g.name}:receive", ["put"], "egress", g.subscribe),
            _rule(f"{g.name}:token", ["liveliness_token"], "ingress", g.tokens),
            _rule(f"{g.name}:watch", ["declare_liveliness_subscriber"], "ingress", g.watch),
            _rule(f"{g.name}:sees", ["liveliness_token"], "egress", g.sees),
            _rule(f"{g.name}:serve", ["declare_queryable"], "ingress", g.serves),
            _rule(f"{g.name}:queried", ["query"], "egress", g.answers),
            _rule(f"{g.name}:reply", ["reply"], "ingress", g.replies),
            _rule(f"{g.name}:ask", ["query"], "ingress", g.asks),
            _rule(f"{g.name}:answered", ["reply"], "egress", g.asks),
            _rule(f"{g.name}:list", ["liveliness_query"], "ingress", g.lists),
        ]
        mine = [r for r in mine if r["key_exprs"]]
        rules += mine
        subjects.append({"id": g.name, "cert_common_names": [cn]})
        policies.append({"id": g.name, "rules": ["declarations-out", "liveliness-interest-out",
                                                 *(r["id"] for r in mine)], "subjects": [g.name]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _rule(rid: str, messages: list[str], flow: str, keys: tuple[str, ...] | list[str]) -> dict[str, Any]:
    return {"id": rid, "messages": messages, "flows": [flow], "permission": "allow", "key_exprs": list(keys)}


def describe(gs: list[Grant]) -> str:
    """A Markdown table of the grants, for the generated guide."""
    lines = ["| identity | may publish | may subscribe to | may declare token | told about tokens | queries |",
             "|---|---|---|---|---|---|"]
    for g in gs:
        queries = [*(f"serves `{x}`" for x in g.serves), *(f"asks `{x}`" for x in g.asks),
                   *(f"lists `{x}`" for x in g.lists)]
        lines.append(f"| `{g.name}` | {_ks(g.publish)} | {_ks(g.subscribe)} | {_ks(g.tokens)} | {_ks(g.sees)} | "
                     f"{'<br>'.join(queries) or '–'} |")
    return "\n".join(lines)


def _ks(keys: tuple[str, ...]) -> str:
    return "<br>".join(f"`{x}`" for x in keys) if keys else "–"
