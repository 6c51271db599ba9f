"""Link profiles: what one directed link ``j -> i`` does to the messages it carries. Pure.

A :class:`LinkProfile` is a strict msgspec Struct (unknown fields are errors, instances are
immutable) whose every field defaults to "no impairment": ``LinkProfile()`` is the identity. The
feature set is that of Linux ``tc netem`` (delay with jitter, distribution and correlation; Bernoulli
and Gilbert-Elliott loss; duplication; reordering with a gap; corruption; a rate limit with a queue)
plus scheduled outages; the model of each, with formulas and the places where it departs from
netem, is in ``docs/netem.md``.

:func:`validate` checks what a type cannot say (ranges, combinations that do nothing) and returns
``(field, message)`` pairs, each message reading ``"<what is wrong>; <how to fix it>"``.
:func:`convert` decodes a raw mapping (a TOML table) into a checked profile. :data:`PRESETS` holds
named profiles; :class:`Network` is a proposed mission section that picks a profile per link and
swaps profiles at given times (:func:`schedule`).
"""

from __future__ import annotations

import math
import types
from collections.abc import Collection, Mapping
from typing import Literal

import msgspec
import msgspec.structs

from tether.schema import Kind, Problems, SchemaError, Strict, close_matches, join, read_issue

# --------------------------------------------------------------------------- delay
Distribution = Literal["uniform", "normal", "pareto"]
"""Shape of the jitter: ``uniform`` on ``[-jitter, +jitter]`` (netem's default), ``normal`` with
standard deviation ``jitter``, ``pareto`` (shape 3, shifted to mean 0, standard deviation
``jitter``; bounded below by ``-jitter/sqrt(3)``, heavy upper tail)."""


class Delay(Strict, frozen=True):
    """Propagation delay of every copy: ``max(0, constant + jitter * Z)``, ``Z`` of mean 0 drawn
    from ``distribution``; successive ``Z`` are correlated by ``correlation`` (``docs/netem.md``)."""

    constant: float = 0.0
    """Mean one-way delay [s] (before the clamp at 0)."""
    jitter: float = 0.0
    """Scale of the delay variation [s]: half-width for ``uniform``, standard deviation for
    ``normal`` and ``pareto``."""
    distribution: Distribution = "uniform"
    correlation: float = 0.0
    """Lag-1 correlation of the latent Gaussian AR(1) that drives ``Z``, in [0, 1); 0 draws each
    delay independently."""


# --------------------------------------------------------------------------- loss
class Bernoulli(Kind, tag="bernoulli", frozen=True):
    """Each message is lost independently with probability ``p``."""

    p: float = 0.0
    """Loss probability, in [0, 1]."""


class GilbertElliott(Kind, tag="gilbert_elliott", frozen=True):
    """Two-state Markov loss (netem ``loss gemodel p r 1-h 1-k``): in state G a message is lost with
    probability ``good_loss`` (= 1-k), in state B with ``bad_loss`` (= 1-h); after each message the
    state moves G -> B with probability ``p`` and B -> G with probability ``r``. Starts in G."""

    p: float = 0.0
    """Transition probability good -> bad, per message, in [0, 1]."""
    r: float | None = None
    """Transition probability bad -> good, per message, in [0, 1]; omitted means ``1 - p`` (as in
    netem). The mean sojourn in B is ``1/r`` messages."""
    bad_loss: float = 1.0
    """Loss probability in the bad state (netem's ``1-h``), in [0, 1]."""
    good_loss: float = 0.0
    """Loss probability in the good state (netem's ``1-k``), in [0, 1]."""

    @property
    def r_eff(self) -> float:
        """``r``, or ``1 - p`` when omitted."""
        return 1.0 - self.p if self.r is None else self.r


Loss = Bernoulli | GilbertElliott


# --------------------------------------------------------------------------- the others
class Reorder(Strict, frozen=True):
    """netem ``reorder p gap g``: a message is *eligible* once ``gap - 1`` messages have taken the
    delay line since the last reordered one; an eligible message skips the delay line with
    probability ``p`` (it is delivered as soon as it is serialised), overtaking earlier messages
    still in flight. Needs a delay to have any effect."""

    p: float = 0.0
    """Probability that an eligible message is reordered, in [0, 1]."""
    gap: int = 1
    """At least ``gap - 1`` delayed messages between two reordered ones; 1 makes every message
    eligible (``gap 5`` with ``p = 1`` reorders messages 5, 10, 15, ...)."""


class Corrupt(Strict, frozen=True):
    """With probability ``p`` a copy has ``bytes`` distinct bytes of its payload XORed with random
    non-zero masks (so each of them differs). An empty payload is delivered unchanged."""

    p: float = 0.0
    """Corruption probability per delivered copy, in [0, 1]."""
    bytes: int = 1
    """Bytes flipped in a corrupted copy (fewer if the payload is shorter), >= 1."""


class Rate(Strict, frozen=True):
    """A FIFO transmitter of ``bytes_per_s``: a copy of ``len(payload) + overhead`` bytes waits for
    the copies ahead of it, then takes ``size / bytes_per_s`` to serialise; the propagation delay
    comes after. ``bytes_per_s = 0`` is no limit."""

    bytes_per_s: float = 0.0
    """Link rate [bytes/s]; 0 is unlimited."""
    overhead: int = 0
    """Bytes added to every payload on the wire (headers) [bytes]."""
    limit: int = 0
    """Copies the transmitter holds (the one being sent included); a copy that finds it full is
    dropped (tail drop). 0 is unbounded."""


Outage = tuple[float, float]
"""``[start, end)`` [s; mission time]: everything sent or arriving in the window is dropped;
``end`` may be ``inf`` (the link never comes back)."""


class LinkProfile(Strict, frozen=True):
    """Everything one directed link does to its messages. ``LinkProfile()`` is the identity."""

    delay: Delay = Delay()
    loss: Loss = Bernoulli()
    duplicate: float = 0.0
    """Probability that a message that is not lost is delivered twice, in [0, 1]."""
    reorder: Reorder = Reorder()
    corrupt: Corrupt = Corrupt()
    rate: Rate = Rate()
    outages: tuple[Outage, ...] = ()
    """``[start, end)`` windows [s; mission time], in any order (their union counts)."""


IDENTITY = LinkProfile()
"""The profile that changes nothing."""


def is_identity(profile: LinkProfile) -> bool:
    """Whether ``profile`` can change nothing: no delay, loss, duplication, reordering, corruption,
    rate limit or outage (a Gilbert-Elliott loss counts as none when ``p = 0`` and ``good_loss =
    0``, the link starting, and so staying, in the good state)."""
    loss = profile.loss
    no_loss = loss.p == 0 and (isinstance(loss, Bernoulli) or loss.good_loss == 0)
    return (profile.delay.constant == 0 and profile.delay.jitter == 0 and no_loss
            and profile.duplicate == 0 and profile.reorder.p == 0 and profile.corrupt.p == 0
            and profile.rate.bytes_per_s == 0 and not profile.outages)


def mean_loss(loss: Loss) -> float:
    """Long-run fraction of messages lost by ``loss`` (outages and queue drops aside).

    Bernoulli: ``p``. Gilbert-Elliott: ``pi_B bad_loss + (1 - pi_B) good_loss`` with the
    stationary probability of the bad state ``pi_B = p / (p + r)`` (0 when ``p = r = 0``).
    """
    if isinstance(loss, Bernoulli):
        return loss.p
    p, r = loss.p, loss.r_eff
    pi_bad = 0.0 if p + r == 0 else p / (p + r)
    return pi_bad * loss.bad_loss + (1.0 - pi_bad) * loss.good_loss


# --------------------------------------------------------------------------- errors
class ProfileError(SchemaError):
    """A link profile (or a network section) is not valid. ``problems`` holds ``(field, message)``
    pairs, each message reading ``"<what is wrong>; <how to fix it>"``."""


# --------------------------------------------------------------------------- validation
def _finite(value: float, field: str, out: Problems) -> bool:
    if not math.isfinite(value):
        out.append((field, f"is {value}; give a finite number"))
        return False
    return True


def _probability(value: float, field: str, out: Problems, example: str = "0.01") -> None:
    if _finite(value, field, out) and not 0.0 <= value <= 1.0:
        name = field.rsplit(".", 1)[-1]
        out.append((field, f"is {value} but a probability is in [0, 1] (a fraction, not a percentage); "
                           f"write e.g. `{name} = {example}` for {float(example) * 100:g} %"))


def _non_negative(value: float, field: str, unit: str, out: Problems, meaning: str) -> None:
    if _finite(value, field, out) and value < 0:
        out.append((field, f"is {value} {unit}; give a value >= 0 ({meaning})"))


def validate(profile: LinkProfile, path: str = "") -> Problems:
    """Every problem of a decoded profile, as ``(field, message-with-fix)`` pairs; ``path`` is
    prefixed to every field (``netem.rules[2].profile``). Empty when the profile is valid."""
    out: Problems = []

    def f(name: str) -> str:
        return join(path, name)

    d = profile.delay
    _non_negative(d.constant, f("delay.constant"), "s", out, "0 is no delay")
    _non_negative(d.jitter, f("delay.jitter"), "s", out, "0 is a constant delay")
    if _finite(d.correlation, f("delay.correlation"), out):
        if not 0.0 <= d.correlation < 1.0:
            out.append((f("delay.correlation"), f"is {d.correlation} but must be in [0, 1) (1 would freeze the "
                                                "jitter); give e.g. `correlation = 0.25`, or 0 for independent "
                                                "delays"))
        elif d.correlation > 0 and d.jitter == 0:
            out.append((f("delay.correlation"), f"is {d.correlation} but delay.jitter is 0, so there is nothing to "
                                                "correlate; set delay.jitter > 0 or remove the correlation"))

    loss = profile.loss
    _probability(loss.p, f("loss.p"), out)
    if isinstance(loss, GilbertElliott):
        if loss.r is not None:
            _probability(loss.r, f("loss.r"), out, example="0.25")
        _probability(loss.bad_loss, f("loss.bad_loss"), out, example="1.0")
        _probability(loss.good_loss, f("loss.good_loss"), out, example="0.0")
        if math.isfinite(loss.p) and 0 < loss.p <= 1 and loss.r_eff == 0:
            why = "r is 0" if loss.r is not None else "r is omitted and p = 1 (r then defaults to 1 - p)"
            out.append((f("loss.r"), f"makes the bad state absorbing ({why}): after the first transition the "
                                     "link stays bad forever; give r > 0 (mean burst 1/r messages, e.g. "
                                     "`r = 0.25`), or use `outages` for a link that goes down"))

    _probability(profile.duplicate, f("duplicate"), out)

    ro = profile.reorder
    _probability(ro.p, f("reorder.p"), out, example="0.05")
    if ro.gap < 1:
        out.append((f("reorder.gap"), f"is {ro.gap}; give a gap >= 1 (1 makes every message eligible for "
                                      "reordering)"))
    if ro.p > 0 and d.constant == 0 and d.jitter == 0:
        out.append((f("reorder.p"), f"is {ro.p} but there is no delay for a reordered message to skip, so "
                                    "nothing is reordered; set delay.constant > 0 (as tc netem requires) or "
                                    "set reorder.p = 0"))

    co = profile.corrupt
    _probability(co.p, f("corrupt.p"), out, example="0.001")
    if co.bytes < 1:
        out.append((f("corrupt.bytes"), f"is {co.bytes}; give the number of bytes to flip in a corrupted "
                                        "message, >= 1"))

    ra = profile.rate
    _non_negative(ra.bytes_per_s, f("rate.bytes_per_s"), "bytes/s", out, "0 is unlimited")
    if ra.overhead < 0:
        out.append((f("rate.overhead"), f"is {ra.overhead} bytes; give the header bytes added per message, "
                                        ">= 0"))
    if ra.limit < 0:
        out.append((f("rate.limit"), f"is {ra.limit}; give the number of messages the queue holds, >= 1, or "
                                     "0 for unbounded"))
    elif ra.limit > 0 and ra.bytes_per_s == 0:
        out.append((f("rate.limit"), f"is {ra.limit} but rate.bytes_per_s is 0 (unlimited), so no queue "
                                     "forms; set rate.bytes_per_s > 0 or remove the limit"))

    for k, (start, end) in enumerate(profile.outages):
        where = f(f"outages[{k}]")
        if not math.isfinite(start):
            out.append((where, f"starts at {start}; give a finite start [s]"))
        elif math.isnan(end):
            out.append((where, f"ends at {end}; give an end [s] after the start, or inf for a link that "
                               "never comes back"))
        elif start < 0:
            out.append((where, f"starts at {start} s, before mission time 0; give a start >= 0"))
        elif not start < end:
            out.append((where, f"is [{start}, {end}), an empty window; give `[start, end]` with start < end "
                               "[s; mission time]"))
    return out


# --------------------------------------------------------------------------- decoding
def _all_field_names() -> list[str]:
    names: set[str] = set()
    for cls in (Delay, Bernoulli, GilbertElliott, Reorder, Corrupt, Rate, LinkProfile):
        names.update(fld.encode_name for fld in msgspec.structs.fields(cls))
    return sorted(names | {"kind"})


_FIELD_NAMES = _all_field_names()


def _from_validation_error(exc: msgspec.ValidationError, path: str) -> tuple[str, str]:
    """Turn msgspec's error at ``$.a.b`` of a profile found at ``path`` into ``(field, message-with-fix)``."""
    issue = read_issue(exc)
    inner = join(path, issue.where) if issue.where else path
    where = inner or "<profile>"
    if issue.kind == "unknown_field" and issue.name is not None:
        close = close_matches(issue.name, _FIELD_NAMES, n=1)
        fix = f"rename it to `{close[0]}` if that is what you meant, or remove it" if close else "remove it"
        return join(inner, issue.name), f"is not a known field; {fix} (see docs/netem.md)"
    if issue.kind == "missing_field" and issue.name == "kind":
        return join(inner, "kind"), ("is missing; say which loss model this is, `kind = \"bernoulli\"` or "
                                     "`kind = \"gilbert_elliott\"`")
    if issue.kind == "invalid_value" and issue.value is not None and where.endswith("kind"):
        return where, "is not a loss model; use \"bernoulli\" or \"gilbert_elliott\""
    if issue.kind == "invalid_value" and issue.value is not None and where.endswith("distribution"):
        return where, "is not a jitter distribution; use \"uniform\", \"normal\" or \"pareto\""
    return where, f"{issue.sentence}; see docs/netem.md for this field's type"


def convert(raw: object, source: str = "<profile>", path: str = "") -> LinkProfile:
    """A checked :class:`LinkProfile` from a raw mapping (a decoded TOML/JSON table), or the preset
    of that name when ``raw`` is a string. Raises :class:`ProfileError` naming every problem (a
    type error stops decoding and is reported alone)."""
    if isinstance(raw, str):
        try:
            return preset(raw)
        except KeyError as exc:
            raise ProfileError(source, [(path or "<profile>", exc.args[0])]) from None
    try:
        profile = msgspec.convert(raw, type=LinkProfile)
    except msgspec.ValidationError as exc:
        raise ProfileError(source, [_from_validation_error(exc, path)]) from None
    problems = validate(profile, path)
    if problems:
        raise ProfileError(source, problems)
    return profile


# --------------------------------------------------------------------------- presets
_STATE_BYTES = 140
"""Typical msgpack size of a ``State`` message [bytes] (3-D, measured on tether.wire)."""

PRESETS: Mapping[str, LinkProfile] = types.MappingProxyType({
    "ideal": IDENTITY,
    "wifi": LinkProfile(
        delay=Delay(constant=0.002, jitter=0.001, distribution="normal", correlation=0.25),
        loss=Bernoulli(p=0.005),
    ),
    "wifi-lossy": LinkProfile(
        delay=Delay(constant=0.004, jitter=0.004, distribution="pareto", correlation=0.25),
        loss=GilbertElliott(p=0.01, r=0.25, bad_loss=0.5, good_loss=0.002),
        duplicate=0.001,
    ),
    "congested": LinkProfile(
        delay=Delay(constant=0.01, jitter=0.01, distribution="pareto", correlation=0.5),
        loss=Bernoulli(p=0.01),
        rate=Rate(bytes_per_s=16_000.0, overhead=48, limit=8),
    ),
    "lossy-burst": LinkProfile(
        delay=Delay(constant=0.003, jitter=0.001, distribution="normal"),
        loss=GilbertElliott(p=0.02, r=0.2, bad_loss=1.0, good_loss=0.0),
    ),
    "hostile": LinkProfile(
        delay=Delay(constant=0.01, jitter=0.005, distribution="pareto", correlation=0.25),
        loss=GilbertElliott(p=0.05, r=0.5, bad_loss=0.8, good_loss=0.01),
        duplicate=0.02,
        reorder=Reorder(p=0.05, gap=2),
        corrupt=Corrupt(p=0.01, bytes=2),
    ),
})
"""Named profiles. The numbers are stated assumptions, not measurements (``docs/netem.md`` gives
the reasoning for each); measure your own links and write a profile when it matters."""

PRESET_NOTES: Mapping[str, str] = types.MappingProxyType({
    "ideal": "the identity: a run with it is bit-identical to a run without netem",
    "wifi": "one uncongested 802.11n/ac hop: a few ms one way, MAC retransmissions leave ~0.5 % loss",
    "wifi-lossy": "edge of range or interference: heavier-tailed delay, ~2 % loss in short bursts",
    "congested": "this link's share of a saturated channel is below the offered load at 100 Hz "
                  f"(~{_STATE_BYTES} B messages): a standing queue of ~0.1 s and tail drops",
    "lossy-burst": "fading episodes: bursts of 5 messages on average (50 ms at 100 Hz), ~9 % loss",
    "hostile": "not a model of any network: every impairment at once, to exercise receivers",
})
"""One line per preset: what it stands for."""


def preset(name: str) -> LinkProfile:
    """The preset ``name``; raises ``KeyError`` whose message lists the presets."""
    try:
        return PRESETS[name]
    except KeyError:
        raise KeyError(_not_a_preset(name)) from None


def _not_a_preset(name: str) -> str:
    close = close_matches(name, list(PRESETS), n=1)
    hint = f"did you mean `{close[0]}`? " if close else ""
    return f"is {name!r}, not a preset; {hint}use one of {', '.join(PRESETS)} or write the profile inline"


# --------------------------------------------------------------------------- network section
class LinkRule(Strict, frozen=True):
    """From ``start`` on, the links matching ``from``/``to`` use ``profile``."""

    profile: str | LinkProfile
    """A preset name or an inline profile."""
    src: int | None = msgspec.field(default=None, name="from")
    """Sender id; omitted matches every sender."""
    dst: int | None = msgspec.field(default=None, name="to")
    """Receiver id; omitted matches every receiver."""
    start: float = 0.0
    """When the rule takes effect [s; mission time]."""


class Network(Strict, frozen=True):
    """A proposed mission section: ``default`` for every link, overridden by ``rules``.

    At mission time ``t`` a link ``j -> i`` uses the profile of the matching rule with the latest
    ``start <= t`` (of equal starts, the one written last), or ``default`` if none matches.
    """

    default: str | LinkProfile = "ideal"
    rules: tuple[LinkRule, ...] = ()
    log: bool = False
    """Keep every link decision (dropped, delayed, duplicated, reordered, corrupted) and write it to
    the run directory as ``netem.jsonl``, for replay and debugging."""


def resolve(p: str | LinkProfile) -> LinkProfile:
    """A profile, or the preset of that name (``KeyError`` if there is none)."""
    return preset(p) if isinstance(p, str) else p


def validate_network(net: Network, node_ids: Collection[int] | None = None, path: str = "netem") -> Problems:
    """Every problem of a network section: unknown presets, invalid inline profiles, bad starts,
    and (when ``node_ids`` is given) ids that are not nodes of the mission."""
    out: Problems = []

    def check(p: str | LinkProfile, where: str) -> None:
        if isinstance(p, str):
            if p not in PRESETS:
                out.append((where, _not_a_preset(p)))
        else:
            out.extend(validate(p, where))

    check(net.default, join(path, "default"))
    for k, rule in enumerate(net.rules):
        where = join(path, f"rules[{k}]")
        check(rule.profile, f"{where}.profile")
        if not math.isfinite(rule.start) or rule.start < 0:
            out.append((f"{where}.start", f"is {rule.start} s; give a start >= 0 [s; mission time]"))
        for name, node in (("from", rule.src), ("to", rule.dst)):
            if node is not None and node_ids is not None and node not in node_ids:
                out.append((f"{where}.{name}", f"is {node}, not a node of the mission; use one of the ids "
                                               f"{sorted(node_ids)}, or omit it to match every node"))
    return out


def schedule(net: Network, src: int, dst: int) -> list[tuple[float, LinkProfile]]:
    """The profiles of link ``src -> dst`` over time: ``[(t0 = 0, p0), (t1, p1), ...]`` with
    ``t`` increasing; ``p_k`` holds on ``[t_k, t_{k+1})``. Consecutive equal profiles are merged.
    Raises ``KeyError`` for an unknown preset (:func:`validate_network` reports it first)."""
    matching = [(rule.start, k, rule) for k, rule in enumerate(net.rules)
                if rule.src in (None, src) and rule.dst in (None, dst)]
    matching.sort(key=lambda item: (item[0], item[1]))
    out: list[tuple[float, LinkProfile]] = [(0.0, resolve(net.default))]
    for start, _, rule in matching:
        prof = resolve(rule.profile)
        if start <= out[-1][0]:
            out[-1] = (out[-1][0], prof)
        else:
            out.append((start, prof))
    merged: list[tuple[float, LinkProfile]] = []
    for t, prof in out:
        if not merged or merged[-1][1] != prof:
            merged.append((t, prof))
    return merged


def profile_at(net: Network, src: int, dst: int, t: float) -> LinkProfile:
    """The profile link ``src -> dst`` uses at mission time ``t`` [s]."""
    changes = schedule(net, src, dst)
    current = changes[0][1]
    for start, prof in changes:
        if start > t:
            break
        current = prof
    return current
