"""One directed link ``j -> i``: what happens to each message offered to it. Pure.

A :class:`Link` lives on the receive side, in the process that subscribes to ``j``. The caller
offers every message it receives from ``j`` with the current mission time, and gets back the
copies to deliver and when (:class:`Delivery`); it holds them until then (:class:`DeliveryQueue`
is a pure holding queue for that). Time is whatever the caller passes, in seconds since tick 0:
simulated seconds in lockstep, monotonic seconds minus tick 0's instant in real time. Nothing here
reads a clock, does I/O or touches global state; randomness comes from the injected
``numpy.random.Generator`` only.

Determinism: the same profile changes, generator seed and offers (``now``, payload) give the same
decisions, bit for bit. The identity profile draws nothing and returns the payload itself at
``now``, so a run with every impairment at zero equals a run without netem.

Model and formulas: ``docs/netem.md``.
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from collections.abc import Iterable

import msgspec
import numpy as np

from tether.netprofile import GilbertElliott, LinkProfile, ProfileError, is_identity, validate

STREAM_KEY = 0x6E65_7465
"""Last word of the seed of every link generator (``"nete"``): keeps link streams apart from the
other generators of a run seeded with ``[seed, ...]`` (a SeedSequence pads short keys with zeros)."""

_STREAMS = ("delay", "loss", "duplicate", "reorder", "corrupt")
"""One child generator per impairment (spawned from the link's generator, in this order), so that
changing one impairment leaves the random realisation of the others unchanged."""

_SQRT2 = math.sqrt(2.0)
_TINY = 1e-300
"""Floor of the Pareto tail probability (reached only for a latent beyond 37 sigma)."""
_PARETO_SHAPE = 3.0
_PARETO_MEAN = _PARETO_SHAPE / (_PARETO_SHAPE - 1.0)
_PARETO_STD = math.sqrt(_PARETO_SHAPE / ((_PARETO_SHAPE - 1.0) ** 2 * (_PARETO_SHAPE - 2.0)))


def batchable(profile: LinkProfile) -> bool:
    """Whether :meth:`Link.offer_times` decides many offers at once under ``profile``: loss (Bernoulli
    or Gilbert-Elliott) and delay (constant or jittered) only, no duplication, reordering, corruption,
    rate limit or outage. Each offer then gives one copy or none, whatever its payload, and what
    becomes of it depends on the times and the link's own generators alone."""
    return (profile.duplicate == 0 and profile.reorder.p == 0 and profile.corrupt.p == 0
            and profile.rate.bytes_per_s <= 0 and not profile.outages)


def link_rng(seed: int, src: int, dst: int) -> np.random.Generator:
    """The generator of link ``src -> dst`` in a run seeded with ``seed``:
    ``numpy.random.default_rng([seed, src, dst, STREAM_KEY])``. Every argument must be >= 0."""
    for name, value in (("seed", seed), ("src", src), ("dst", dst)):
        if value < 0:
            raise ValueError(f"{name} is {value}; link generators take ids and seeds >= 0")
    return np.random.default_rng([seed, src, dst, STREAM_KEY])


class Delivery(msgspec.Struct, frozen=True):
    """One copy of an offered message, to be handed to the receiver at ``at``."""

    at: float
    """Delivery time [s; the caller's time base], >= the offer's ``now``."""
    payload: bytes
    """The bytes to deliver: the offered payload itself unless corrupted."""
    event: str
    """``deliver`` (the message) or ``duplicate`` (its extra copy), then ``+reorder`` if it skipped
    the delay line and ``+corrupt`` if its bytes were flipped: e.g. ``deliver+corrupt``."""

    @property
    def duplicate(self) -> bool:
        return self.event.startswith("duplicate")

    @property
    def reordered(self) -> bool:
        return "+reorder" in self.event

    @property
    def corrupted(self) -> bool:
        return "+corrupt" in self.event


class Decision(msgspec.Struct, frozen=True):
    """One line of a link's decision log: what became of one copy of offer ``seq``."""

    seq: int
    """Index of the offer on this link, from 0."""
    now: float
    """The offer's time [s]."""
    event: str
    """A :attr:`Delivery.event`, or ``drop:loss``, ``drop:outage``, ``drop:queue``."""
    at: float | None
    """Delivery time [s]; None for a drop."""


DROP_REASONS = ("loss", "outage", "queue")
"""Why a copy can be dropped: the loss model, a scheduled outage, a full rate-limit queue."""


class Link:
    """The state of one directed link and its randomness.

    ``offer(now, payload)`` returns the copies to deliver (empty: dropped, and
    :attr:`last_drop_reason` says why). ``now`` must not decrease from one offer to the next.
    Calls never block and never raise for a valid profile and time.
    """

    def __init__(self, profile: LinkProfile, rng: np.random.Generator, *, log: bool = False):
        """``rng`` must be dedicated to this link (see :func:`link_rng`); the link spawns one child
        generator per impairment from it (``Generator.spawn``, which draws nothing). ``log`` keeps a
        :class:`Decision` per copy in :attr:`decisions`. Raises :class:`ProfileError`."""
        self._check(profile)
        self._profile = profile
        self._identity = is_identity(profile)
        self._rng = dict(zip(_STREAMS, rng.spawn(len(_STREAMS)), strict=True))
        self._seq = 0
        self._last_now = -math.inf
        self._ge_bad = False
        """Gilbert-Elliott state: in the bad state."""
        self._latent: float | None = None
        """Last value of the latent AR(1) behind the jitter (None before the first draw)."""
        self._since_reorder = 0
        """Messages that took the delay line since the last reordered one (netem's counter)."""
        self._busy_until = -math.inf
        """When the transmitter finishes the last copy queued [s]."""
        self._in_queue: deque[float] = deque()
        """Finish times of the copies queued or being sent, oldest first."""
        self.last_drop_reason: str | None = None
        """Why the last offer returned no copy (one of :data:`DROP_REASONS`); None if it did."""
        self.counts: dict[str, int] = {"offered": 0, "delivered": 0, "duplicate": 0, "reorder": 0,
                                       "corrupt": 0, **{r: 0 for r in DROP_REASONS}}
        """Offers, copies delivered, and copies duplicated, reordered, corrupted, dropped by reason."""
        self.decisions: list[Decision] | None = [] if log else None
        """The decision log (when ``log``), one :class:`Decision` per copy, in offer order."""

    @staticmethod
    def _check(profile: LinkProfile) -> None:
        if not isinstance(profile, LinkProfile):
            raise TypeError(f"a link takes a LinkProfile, not {type(profile).__name__}")
        problems = validate(profile)
        if problems:
            raise ProfileError("<link profile>", problems)

    @property
    def profile(self) -> LinkProfile:
        return self._profile

    def set_profile(self, profile: LinkProfile) -> None:
        """Use ``profile`` for the offers from now on; copies already returned keep their times.

        Kept across the change: the offer count, the latent jitter state (a correlated jitter goes
        on smoothly), the reorder counter, the transmitter's backlog (copies already queued finish
        at the old rate; new ones queue behind them when the new profile has a rate, and bypass
        the transmitter when it has none), and the Gilbert-Elliott state when both the old and the
        new loss models are Gilbert-Elliott (otherwise the link starts in the good state).
        Raises :class:`ProfileError`.
        """
        self._check(profile)
        if not isinstance(profile.loss, GilbertElliott):
            self._ge_bad = False
        self._profile = profile
        self._identity = is_identity(profile)

    @property
    def last_offer(self) -> float:
        """Time of the newest offer [s]; -inf before the first."""
        return self._last_now

    def take_decisions(self) -> list[Decision]:
        """The decisions logged since the last call, and forget them (bounded memory in long runs)."""
        if self.decisions is None:
            return []
        out, self.decisions = self.decisions, []
        return out

    # ------------------------------------------------------------------- the decision
    def offer(self, now: float, payload: bytes) -> list[Delivery]:
        """Decide what happens to ``payload`` offered at ``now`` [s]: the copies to deliver, each
        with its time ``at >= now`` (empty if dropped). Returns immediately.

        Order: outage at ``now`` -> loss -> duplication -> reordering decision -> per copy:
        rate-limit queue, delay, outage at ``at``, corruption. Raises ``ValueError`` when ``now`` is
        not finite or earlier than the previous offer's."""
        if not math.isfinite(now) or now < self._last_now:
            raise ValueError(f"now is {now} but offers need a finite time that does not decrease "
                             f"(previous offer at {self._last_now})")
        self._last_now = now
        seq = self._seq
        self._seq += 1
        self.counts["offered"] += 1

        if self._identity and not self._ge_bad:
            self._since_reorder += 1
            self.last_drop_reason = None
            self.counts["delivered"] += 1
            if self.decisions is not None:
                self.decisions.append(Decision(seq, now, "deliver", now))
            return [Delivery(now, payload, "deliver")]

        prof = self._profile
        if self._in_outage(now):
            return self._drop(seq, now, "outage")
        if self._lost():
            return self._drop(seq, now, "loss")
        copies = 2 if self._happens("duplicate", prof.duplicate) else 1

        ro = prof.reorder
        reordered = False
        if ro.p > 0 and self._since_reorder >= ro.gap - 1 and self._happens("reorder", ro.p):
            reordered = True
            self._since_reorder = 0
        else:
            self._since_reorder += 1

        out: list[Delivery] = []
        reasons: list[str] = []
        for copy in range(copies):
            role = "duplicate" if copy else "deliver"
            depart = self._transmit(now, len(payload))
            if depart is None:
                reasons.append(self._log_drop(seq, now, "queue"))
                continue
            delay = self._delay()
            skip = reordered and copy == 0
            at = depart if skip else depart + delay
            if self._in_outage(at):
                reasons.append(self._log_drop(seq, now, "outage"))
                continue
            data, corrupted = self._corrupt(payload)
            event = role + ("+reorder" if skip else "") + ("+corrupt" if corrupted else "")
            self.counts["delivered"] += 1
            self.counts["duplicate"] += copy
            self.counts["reorder"] += skip
            self.counts["corrupt"] += corrupted
            if self.decisions is not None:
                self.decisions.append(Decision(seq, now, event, at))
            out.append(Delivery(at, data, event))
        self.last_drop_reason = None if out else reasons[0]
        return out

    def offer_times(self, now: np.ndarray) -> np.ndarray:
        """:meth:`offer` of one message at each time of ``now`` (finite, non-decreasing, none before
        the previous offer), for a profile :func:`batchable` says yes to: each offer's delivery time,
        NaN where it was lost. Draws exactly what the offers one by one draw, from the same streams
        in the same order, and leaves the link as they would (counts, generators, Gilbert-Elliott
        state, jitter's latent, last drop reason). Raises ``ValueError`` for another profile, for a
        link that keeps a decision log, or for times :meth:`offer` would refuse (nothing changed)."""
        prof = self._profile
        if not batchable(prof) or self.decisions is not None:
            raise ValueError("offer_times takes a link without a decision log whose profile is batchable "
                             "(loss and delay only)")
        now = np.asarray(now, dtype=float)
        n = len(now)
        if n == 0:
            return np.empty(0)
        if (not np.all(np.isfinite(now)) or bool(np.any(np.diff(now) < 0.0))
                or not float(now[0]) >= self._last_now):
            raise ValueError(f"offer times must be finite and non-decreasing from the previous offer "
                             f"({self._last_now}); first {float(now[0])}")
        if self._identity and not self._ge_bad:  # offer's first branch: nothing drawn, nothing changed
            lost = np.zeros(n, dtype=bool)
        elif isinstance(prof.loss, GilbertElliott):
            lost = self._chain(prof.loss, n)
        else:
            p = prof.loss.p
            if p <= 0.0:  # as _happens: a certain outcome draws nothing
                lost = np.zeros(n, dtype=bool)
            elif p >= 1.0:
                lost = np.ones(n, dtype=bool)
            else:
                lost = self._rng["loss"].random(n) < p  # the same doubles, in order, as n calls of random()
        kept = np.nonzero(~lost)[0]
        at = np.full(n, math.nan)
        # each copy kept: depart (no rate limit: now) plus its delay, as offer adds them
        at[kept] = now[kept] + self._delays(len(kept))
        dropped = n - len(kept)
        self._last_now = float(now[-1])
        self._seq += n
        self._since_reorder += n - dropped
        self.counts["offered"] += n
        self.counts["delivered"] += n - dropped
        self.counts["loss"] += dropped
        self.last_drop_reason = "loss" if lost[-1] else None
        return at

    def _chain(self, loss: GilbertElliott, n: int) -> np.ndarray:
        """:meth:`_lost` for ``n`` offers in a row: the loss decisions, the state moved along. Each
        offer draws 0, 1 or 2 doubles (a certain outcome draws none), so at most ``2 n`` are drawn
        ahead and the generator is then put where the ones used leave it (``advance``: the
        generators are PCG64, one 64-bit step per double)."""
        stream = self._rng["loss"]
        if (loss.good_loss in (0.0, 1.0) and loss.bad_loss in (0.0, 1.0)
                and 0.0 < loss.p < 1.0 and 0.0 < loss.r_eff < 1.0):
            return self._two_states(loss, stream.random(n))
        bits = stream.bit_generator
        before = bits.state
        # a generator that cannot be advanced (not PCG64) draws one double at a time
        ahead = stream.random(2 * n).tolist() if hasattr(bits, "advance") else None
        used = 0
        bad = self._ge_bad
        lost = np.empty(n, dtype=bool)
        probs = (loss.good_loss, loss.bad_loss)
        moves = (loss.p, loss.r_eff)
        for s in range(n):
            for step in (0, 1):
                prob = (probs if step == 0 else moves)[bad]
                if prob <= 0.0:
                    hit = False
                elif prob >= 1.0:
                    hit = True
                else:
                    hit = (ahead[used] if ahead is not None else stream.random()) < prob
                    used += 1
                if step == 0:
                    lost[s] = hit
                else:
                    bad = not hit if bad else hit
        if ahead is not None:
            bits.state = before
            getattr(bits, "advance")(used)  # PCG64's (checked above; BitGenerator does not declare it)
        self._ge_bad = bad
        return lost

    def _two_states(self, loss: GilbertElliott, u: np.ndarray) -> np.ndarray:
        """:meth:`_chain` when each offer's loss is certain in either state (``good_loss`` and
        ``bad_loss`` 0 or 1) and each move is not (``p`` and ``r`` strictly between 0 and 1): one
        double per offer, ``u``, decides the move. Each offer then sets the state (both states go to
        the same one), keeps it or flips it, so the state before offer s is the last state set before
        it, flipped once per flip since: whole arrays, no loop."""
        n = len(u)
        to_bad_from_good = u < loss.p  # _happens("loss", p) in the good state
        to_bad_from_bad = ~(u < loss.r_eff)  # not _happens("loss", r) in the bad state
        fixed = to_bad_from_good == to_bad_from_bad  # the next state whatever this one
        flips = to_bad_from_good & ~to_bad_from_bad
        idx = np.arange(n)
        # state before offer s + 1, for s = 0 .. n-1: the last fixed move at or before s, then flips
        last = np.maximum.accumulate(np.where(fixed, idx, -1))
        flips_upto = np.cumsum(flips)
        start = np.where(last >= 0, to_bad_from_good[np.maximum(last, 0)], self._ge_bad)
        flipped: np.ndarray = flips_upto - np.where(last >= 0, flips_upto[np.maximum(last, 0)], 0)
        after = start ^ (flipped % 2 == 1)
        before = np.concatenate([[self._ge_bad], after[:-1]])
        self._ge_bad = bool(after[-1])
        return np.where(before, loss.bad_loss >= 1.0, loss.good_loss >= 1.0)

    def _delays(self, m: int) -> np.ndarray:
        """:meth:`_delay` for ``m`` copies in a row (the jitter's normals drawn at once: the same
        doubles, in order, as ``m`` calls; its latent moved along)."""
        d = self._profile.delay
        if d.jitter <= 0:
            return np.full(m, d.constant)
        eps = self._rng["delay"].standard_normal(m).tolist()
        rho = d.correlation
        keep = math.sqrt(1.0 - rho * rho)
        latent = self._latent
        out = np.empty(m)
        for c, e in enumerate(eps):
            g = e if latent is None else rho * latent + keep * e
            latent = g
            out[c] = max(0.0, d.constant + d.jitter * _shape(d.distribution, g))
        self._latent = latent
        return out

    # ------------------------------------------------------------------- parts
    def _happens(self, stream: str, prob: float) -> bool:
        """A Bernoulli(prob) draw from ``stream``; certain outcomes draw nothing."""
        if prob <= 0.0:
            return False
        if prob >= 1.0:
            return True
        return bool(self._rng[stream].random() < prob)

    def _drop(self, seq: int, now: float, reason: str) -> list[Delivery]:
        self.last_drop_reason = self._log_drop(seq, now, reason)
        return []

    def _log_drop(self, seq: int, now: float, reason: str) -> str:
        self.counts[reason] += 1
        if self.decisions is not None:
            self.decisions.append(Decision(seq, now, f"drop:{reason}", None))
        return reason

    def _in_outage(self, t: float) -> bool:
        outages = self._profile.outages
        return bool(outages) and any(start <= t < end for start, end in outages)

    def _lost(self) -> bool:
        """The loss model's decision for this message; moves the Gilbert-Elliott chain."""
        loss = self._profile.loss
        if not isinstance(loss, GilbertElliott):
            return self._happens("loss", loss.p)
        bad = self._ge_bad
        lost = self._happens("loss", loss.bad_loss if bad else loss.good_loss)
        self._ge_bad = not self._happens("loss", loss.r_eff) if bad else self._happens("loss", loss.p)
        return lost

    def _transmit(self, now: float, size: int) -> float | None:
        """When a copy of ``size`` payload bytes offered at ``now`` leaves the transmitter [s], or
        None if the queue is full. Without a rate, ``now``."""
        rate = self._profile.rate
        if rate.bytes_per_s <= 0:
            return now
        queue = self._in_queue
        while queue and queue[0] <= now:
            queue.popleft()
        if rate.limit and len(queue) >= rate.limit:
            return None
        finish = max(now, self._busy_until) + (size + rate.overhead) / rate.bytes_per_s
        self._busy_until = finish
        queue.append(finish)
        return finish

    def _delay(self) -> float:
        """The propagation delay of one copy [s]: ``max(0, constant + jitter * Z)``."""
        d = self._profile.delay
        if d.jitter <= 0:
            return d.constant
        eps = float(self._rng["delay"].standard_normal())
        rho = d.correlation
        g = eps if self._latent is None else rho * self._latent + math.sqrt(1.0 - rho * rho) * eps
        self._latent = g
        return max(0.0, d.constant + d.jitter * _shape(d.distribution, g))

    def _corrupt(self, payload: bytes) -> tuple[bytes, bool]:
        """The copy's bytes and whether they were corrupted."""
        co = self._profile.corrupt
        if not payload or not self._happens("corrupt", co.p):
            return payload, False
        rng = self._rng["corrupt"]
        m = min(co.bytes, len(payload))
        where = rng.choice(len(payload), size=m, replace=False)
        masks = rng.integers(1, 256, size=m)
        data = bytearray(payload)
        for pos, mask in zip(where.tolist(), masks.tolist(), strict=True):
            data[pos] ^= mask
        return bytes(data), True


def _shape(distribution: str, g: float) -> float:
    """Map a standard normal ``g`` to the jitter variable ``Z`` (mean 0) of ``distribution`` by
    its quantile function: the Gaussian copula that keeps each marginal exact under correlation."""
    if distribution == "normal":
        return g
    if distribution == "uniform":
        return math.erf(g / _SQRT2)  # 2 Phi(g) - 1, uniform on (-1, 1)
    upper = max(0.5 * math.erfc(g / _SQRT2), _TINY)  # 1 - Phi(g), accurate in the upper tail
    x = upper ** (-1.0 / _PARETO_SHAPE)  # Pareto(shape 3, scale 1): P(X > x) = x^-3
    return (x - _PARETO_MEAN) / _PARETO_STD


class DeliveryQueue:
    """Copies not yet due, released in order of ``at`` (equal times: in the order pushed).

    One per receiving process, or one per link: pure, no clock. In lockstep, release at each tick
    what is due by ``t_k``; in real time, wake at :attr:`next_at`.
    """

    def __init__(self) -> None:
        self._heap: list[tuple[float, int, Delivery]] = []
        self._pushed = 0

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, deliveries: Iterable[Delivery]) -> None:
        for d in deliveries:
            heapq.heappush(self._heap, (d.at, self._pushed, d))
            self._pushed += 1

    @property
    def next_at(self) -> float | None:
        """The earliest delivery time held [s], or None when empty."""
        return self._heap[0][0] if self._heap else None

    def pop_due(self, now: float) -> list[Delivery]:
        """Every copy with ``at <= now``, earliest first."""
        out = []
        while self._heap and self._heap[0][0] <= now:
            out.append(heapq.heappop(self._heap)[2])
        return out
