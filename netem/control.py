"""Run-time control of the emulated network: ``tether netem-set`` and the service agents run.

A change of the emulated network is a Zenoh query carrying a :class:`~tether.wire.NetemSet` on
``tether/<ns>/agent/<id>/netem`` (every agent, or the receivers a rule names); each agent applies
it to its in-links and answers with what changed, so the caller knows which links took it and
from when. Agents that do not answer within the timeout are reported.
"""

from __future__ import annotations

import json
import logging
import math
import tomllib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import msgspec
import zenoh

from tether import jsonout
from tether import transport as tp
from tether import wire
from tether.netprofile import LinkProfile, LinkRule, Network, ProfileError, convert, resolve, validate_network

if TYPE_CHECKING:
    from tether.node import Node

log = logging.getLogger("tether")


@dataclass(frozen=True)
class Answer:
    node: int | None
    changed: list[dict]
    error: str | None = None


def parse_profile(text: str) -> str | LinkProfile:
    """A preset name (``wifi-lossy``) or an inline TOML table (``{ loss = { p = 0.2 } }``).
    Raises :class:`~tether.netprofile.ProfileError` naming the field."""
    text = text.strip()
    if not text.startswith("{"):
        return text
    try:
        raw = tomllib.loads(f"profile = {text}")["profile"]
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError("PROFILE", [("<profile>", f"is not a TOML inline table: {exc}; "
                                                      'write it like { delay = { constant = 0.05 } }')]) from None
    return convert(raw, "PROFILE")


async def netem_set(settings: tp.ZenohSettings, ns: str, rule: LinkRule, at: float | None,
                    timeout: float = 5.0) -> list[Answer]:
    """Ask the agents of namespace ``ns`` (those ``rule.dst`` names, or all) to apply ``rule`` from
    mission time ``at`` (None: on receipt). Returns one answer per agent that replied."""
    keys = wire.Keys(ns)
    target = keys.topic("agent", rule.dst, "netem") if rule.dst is not None else f"tether/{ns}/agent/*/netem"
    msg = wire.NetemSet(sender=0, seq=0, k=0, t=0.0, rules=[rule], at=at)
    answers: list[Answer] = []
    async with tp.open_session(settings) as session:
        def agents_up() -> list[int]:
            up = []
            for r in session.liveliness().get(keys.token("agent", "*"), timeout=timeout):
                if r.ok is None:
                    continue
                try:
                    up.append(wire.Keys.parse_token(str(r.ok.key_expr))[1])
                except ValueError:  # a token on a malformed key: not an agent
                    pass
            return sorted(up)

        if rule.dst is not None:  # connected, and that agent is up (it may still be starting)
            try:
                await tp.wait_for_tokens(session, [keys.token("agent", rule.dst)], timeout)
            except tp.TokensMissing:
                up = agents_up()
                raise TimeoutError(f"agent {rule.dst} is not up in namespace {ns!r} after {timeout:g} s "
                                   f"(agents up: {', '.join(map(str, up)) or 'none'}); check --to and --ns") from None
        replies = session.get(target, payload=wire.encode(msg), timeout=timeout,
                              target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE)
        for reply in replies:  # blocks until every queryable answered or the timeout
            if reply.ok is not None:
                body = json.loads(reply.ok.payload.to_bytes())
                answers.append(Answer(body["node"], body["changed"], body.get("error")))
            elif reply.err is not None:
                answers.append(Answer(None, [], reply.err.payload.to_string()))
        present = agents_up()
    missing = [i for i in present if i not in {a.node for a in answers} and rule.dst in (None, i)]
    answers += [Answer(i, [], "did not answer in time") for i in missing]
    return answers


def rule_of(profile: str | LinkProfile, src: int | None, dst: int | None) -> LinkRule:
    return msgspec.structs.replace(LinkRule(profile=profile), src=src, dst=dst)


# --------------------------------------------------------------------------- the agents' side
def serve(node: "Node") -> None:
    """Serve ``tether netem-set`` on ``tether/<ns>/<role>/<id>/netem``: a query carrying a
    :class:`~tether.wire.NetemSet` changes this node's emulated in-links at run time and is answered
    with what changed, or why nothing did: a malformed message, invalid rules, or a mission without
    a ``[netem]`` section, whose links bypass the emulator (those are also counted as
    ``netem_invalid``)."""
    key = node.keys.topic(node.args.role, node.args.node_id, "netem")

    def refuse(query: zenoh.Query, why: str) -> None:
        # a reply on its own key, not reply_err: an error reply travels on the query's key, which for
        # `agent/*/netem` the access rules cannot let an agent reply on without letting it answer for others
        query.reply(key, jsonout.dumps({"node": node.args.node_id, "changed": [], "error": why}, indent=None))

    def handle(query: zenoh.Query) -> None:
        payload = query.payload
        msg = node.receiver.accept(payload.to_bytes() if payload is not None else b"", wire.NetemSet, 0)
        if msg is None:
            refuse(query, "not a valid NetemSet message (see tether.wire); nothing changed")
            return
        try:
            done = apply(node, msg)
        except ValueError as exc:
            node.count_drop("netem_invalid")
            log.error("netem change refused: %s", exc)
            refuse(query, f"{node.args.role} {node.args.node_id}: refused: {exc}")
            return
        # on its own key, even to a wildcard query: the access rules let an agent reply for itself only
        query.reply(key, jsonout.dumps({"node": node.args.node_id, "changed": done}, indent=None))

    node.queryable(key, handle)


def apply(node: "Node", msg: wire.NetemSet) -> list[dict[str, Any]]:
    """Apply a change to the node's matching in-links; returns ``[{src, dst, at}]``. Raises ValueError."""
    m = node.mission
    me = node.args.node_id
    ids = [*m.agent_ids, m.leader.id]
    problems = validate_network(Network(rules=tuple(msg.rules)), ids, path="rules")
    if msg.at is not None and not (math.isfinite(msg.at) and msg.at >= 0):
        problems.append(("at", f"is {msg.at}; give a mission time >= 0 [s], or none for 'now'"))
    if m.netem is None:
        problems.append(("netem", "the mission has no [netem] section, so its links bypass the emulator; "
                                  'add `[netem]` with `default = "ideal"` to change links at run time'))
    if problems:
        raise ValueError("; ".join(f"{f} {m}" for f, m in problems))
    from netem.link import Channel  # loaded with the mission's [netem] section only

    channels = {s.sender: s.channel for s in node.sources.values() if isinstance(s.channel, Channel)}
    done = []
    for rule in msg.rules:
        if rule.dst not in (None, me):
            continue
        prof = resolve(rule.profile)
        for src, ch in sorted(channels.items()):
            if rule.src not in (None, src):
                continue
            now = max(ch.last_offer, 0.0)  # before the first offer: from tick 0
            at = msg.at if msg.at is not None else node.clock.link_time(now)
            if at < now:
                log.warning("netem change of link %d -> %d for t = %.3f s arrived at t = %.3f s: "
                            "applied from the next sample", src, me, at, now)
            ch.change(at, prof)
            done.append({"src": src, "dst": me, "at": max(at, now)})
            log.info("link %d -> %d: profile changed from t = %.3f s", src, me, max(at, now))
    return done
