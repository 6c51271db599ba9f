"""Run-time control of a running swarm from outside: ``tether netem-set``.

A change of the emulated network is a Zenoh query carrying a :class:`~tether.wire.NetemSet` on
``tether/<ns>/agent/<id>/netem`` (every agent, or the receivers a rule names); each agent applies
it to its in-links and answers with what changed, so the caller knows which links took it and
from when. Agents that do not answer within the timeout are reported.
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass

import msgspec
import zenoh

from netem.profile import LinkProfile, LinkRule, ProfileError, convert
from tether import transport as tp
from tether import wire


@dataclass(frozen=True)
class Answer:
    node: int | None
    changed: list[dict]
    error: str | None = None


def parse_profile(text: str) -> str | LinkProfile:
    """A preset name (``wifi-lossy``) or an inline TOML table (``{ loss = { p = 0.2 } }``).
    Raises :class:`~netem.profile.ProfileError` naming the field."""
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
            return sorted(wire.Keys.parse_token(str(r.ok.key_expr))[1]
                          for r in session.liveliness().get(keys.token("agent", "*"), timeout=timeout)
                          if r.ok is not None)

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
                answers.append(Answer(body["node"], body["changed"]))
            else:
                answers.append(Answer(None, [], reply.err.payload.to_string()))
        present = agents_up()
    missing = [i for i in present if i not in {a.node for a in answers} and rule.dst in (None, i)]
    answers += [Answer(i, [], "did not answer in time") for i in missing]
    return answers


def rule_of(profile: str | LinkProfile, src: int | None, dst: int | None) -> LinkRule:
    return msgspec.structs.replace(LinkRule(profile=profile), src=src, dst=dst)
