"""Radios: which Crazyflies share a dongle, and how healthy each vehicle's link is. Pure (no I/O,
no clock: the caller gives the time).

* :func:`dongles` is the grouping rule, one definition for ``tether run`` (one radio host process
  per dongle, :mod:`cli.radio`), ``--sitl`` (one software radio per group, :mod:`deploy.sitl`) and the
  deployment generator. cflib shares a Crazyradio only among the links of one process (a second
  process gets "device busy"), so every vehicle on a dongle must be flown from one process.
* :class:`LinkMonitor` judges one vehicle's link from what the plant can count itself on any cflib
  driver: the share of the expected log packets that came (the downlink's delivery rate; on a radio,
  the acknowledgements that carried them) and the pings' median round trip, both over the last window.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from urllib.parse import urlsplit

SIM_RADIO_SIZE = 4
"""Software Crazyflies (``udp://``) per simulated dongle: those of one host, in port order, in groups
of this many (the radio budget of ``docs/crazyflie.md`` fits four at the plant's default rates)."""


@dataclass(frozen=True)
class Dongle:
    """One radio and the agents flown through it."""

    name: str
    """``radio://N`` (a Crazyradio, as cflib numbers or names it), ``sim://HOST/G`` (a simulated one)
    or ``usb://N`` / the URI itself (a vehicle with a link of its own)."""
    agents: tuple[int, ...]
    """Agent ids, in mission order (simulated: port order)."""

    @property
    def simulated(self) -> bool:
        return self.name.startswith("sim://")


def dongles(vehicles: Sequence[tuple[int, str]], sim_size: int = SIM_RADIO_SIZE) -> list[Dongle]:
    """Group ``(agent id, URI)`` pairs by the dongle that carries them: ``radio://N/...`` by ``N``;
    ``udp://HOST:PORT`` by host, in port order, ``sim_size`` to a simulated dongle; anything else
    (``usb://``) alone. Groups come in the order of their first vehicle."""
    if sim_size < 1:
        raise ValueError(f"sim_size = {sim_size}: give at least 1 vehicle per simulated radio")
    named: dict[str, list[int]] = {}
    sims: dict[str, list[tuple[int, int]]] = {}
    order: list[str] = []
    for aid, uri in vehicles:
        u = urlsplit(uri)
        if u.scheme == "radio":
            key = f"radio://{u.netloc}"
        elif u.scheme == "udp" and u.port is not None:
            key = f"sim://{u.hostname}"
            sims.setdefault(key, []).append((u.port, aid))
        else:
            key = uri
        if key not in order:
            order.append(key)
        if not key.startswith("sim://"):
            named.setdefault(key, []).append(aid)
    out: list[Dongle] = []
    for key in order:
        if key in sims:
            ids = [aid for _, aid in sorted(sims[key])]
            out += [Dongle(f"{key}/{g}", tuple(ids[i:i + sim_size]))
                    for g, i in enumerate(range(0, len(ids), sim_size))]
        else:
            out.append(Dongle(key, tuple(named[key])))
    return out


@dataclass(frozen=True)
class LinkLimits:
    """When a link is worth a warning and when it is no longer fit to fly."""

    window: float = 1.0
    """Span [s] over which the delivery rate is counted."""
    warn_rate: float = 0.9
    """Below this share of the expected log packets: a warning (Crazyswarm2's threshold)."""
    fail_rate: float = 0.5
    """Below this share, held for ``fail_after``: the link has failed."""
    warn_latency: float = 0.05
    """A ping round trip beyond this [s]: a warning."""
    fail_latency: float = 0.25
    """A ping round trip beyond this [s], held for ``fail_after``: the link has failed (the vehicle
    flies on data this old, and its commands arrive as late)."""
    fail_after: float = 4.0
    """How long [s] a failing measure must last: as long as a silent link is given to speak again
    (``plant.crazyflie.RELINK_AFTER``), so that a brief fade, or a starved host, is ridden out as an
    outage is, and only a link that stays poor lands its vehicle."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.fail_rate <= self.warn_rate <= 1.0:
            raise ValueError(f"link limits: need 0 <= fail_rate <= warn_rate <= 1, got {self.fail_rate}, "
                             f"{self.warn_rate}")
        if not 0.0 < self.warn_latency <= self.fail_latency:
            raise ValueError(f"link limits: need 0 < warn_latency <= fail_latency, got {self.warn_latency}, "
                             f"{self.fail_latency}")
        if not (self.window > 0.0 and self.fail_after >= 0.0):
            raise ValueError("link limits: window must be > 0 and fail_after >= 0 [s]")


OK, WARN, FAIL = "ok", "warn", "fail"


@dataclass(frozen=True)
class LinkReport:
    """A judgement of the link at one instant."""

    state: str
    """:data:`OK`, :data:`WARN` or :data:`FAIL`."""
    rate: float
    """Share of the expected log packets that came within the last window (0..1)."""
    latency: float
    """Newest ping round trip [s] (0 before the first)."""
    why: str


class LinkMonitor:
    """Counts one vehicle's log packets and ping round trips; :meth:`judge` says whether the link is
    fine, worth a warning, or failed (a failing measure held for ``fail_after``; once failed, it
    stays failed: the plant lands the vehicle). ``expected``: log packets per second the vehicle was
    asked for (every block's rate summed)."""

    def __init__(self, expected: float, limits: LinkLimits | None = None) -> None:
        if not expected > 0.0:
            raise ValueError(f"expected = {expected!r}: give the log packets per second asked for (> 0)")
        self.limits = limits or LinkLimits()
        self.expected = expected
        self._arrivals: deque[float] = deque()
        self._pongs: deque[tuple[float, float]] = deque()
        self._start: float | None = None
        self.latency = 0.0
        """Median ping round trip [s] over the last window (0 while none came)."""
        self._bad_since: float | None = None
        self.failed: LinkReport | None = None

    def packet(self, now: float) -> None:
        """A log packet came at ``now`` [s]."""
        if self._start is None:
            self._start = now
        self._arrivals.append(now)

    def round_trip(self, now: float, seconds: float) -> None:
        """A ping came back at ``now`` [s] after ``seconds``."""
        self._pongs.append((now, seconds))

    def judge(self, now: float) -> LinkReport:
        """The link's state at ``now`` [s] (see the class docstring)."""
        if self.failed is not None:
            return self.failed
        lim = self.limits
        while self._arrivals and self._arrivals[0] <= now - lim.window:
            self._arrivals.popleft()
        while self._pongs and self._pongs[0][0] <= now - lim.window:
            self._pongs.popleft()
        rtts = sorted(r for _, r in self._pongs)
        self.latency = rtts[len(rtts) // 2] if rtts else 0.0  # the median: one stalled ping is no trend
        if self._start is None or now - self._start < lim.window:  # not a whole window yet
            return LinkReport(OK, 1.0, self.latency, "")
        rate = min(1.0, len(self._arrivals) / (self.expected * lim.window))
        failing = rate < lim.fail_rate or self.latency > lim.fail_latency
        why = f"{100 * rate:.0f} % of the log packets in {lim.window:g} s, ping {1000 * self.latency:.0f} ms"
        if failing:
            self._bad_since = now if self._bad_since is None else self._bad_since
            if now - self._bad_since >= lim.fail_after:
                self.failed = LinkReport(FAIL, rate, self.latency, why)
                return self.failed
        else:
            self._bad_since = None
        if rate < lim.warn_rate or self.latency > lim.warn_latency:
            return LinkReport(WARN, rate, self.latency, why)
        return LinkReport(OK, rate, self.latency, why)
