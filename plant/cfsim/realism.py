"""Optional realism of the software Crazyflie: estimator noise, a draining battery, a lossy and late
link. Pure (no sockets, no clock); every random draw comes from a generator seeded by the caller, so
a seed and the sequence of calls fix every outcome. All three are off by default.

* :class:`EstimatorNoise`: the onboard state estimate is the truth plus a first-order Gauss-Markov
  (Ornstein-Uhlenbeck) error per axis, stationary standard deviation ``sigma_p`` [m] on position and
  ``sigma_v`` [m/s] on velocity, correlation time ``tau`` [s]. An estimator fusing a 0.1 m ranging
  system (the Loco Positioning System) has an error of that size that wanders rather than jumping
  every 10 ms; the position controller flies on the estimate, so the vehicle itself wanders too.
* :class:`Battery`: a 1-cell LiPo of ``capacity_mah`` whose current grows with the collective thrust
  (``idle_a`` + ``hover_a * (T / T_hover)^1.5``); the open-circuit voltage falls linearly with the
  charge from ``v_full`` to ``v_empty`` and sags by ``r_internal * I``. Once the (loaded) voltage has
  stayed below ``v_low`` for ``low_delay`` the power state is *low power* (3; the firmware's
  ``PM_BAT_LOW_VOLTAGE`` 3.2 V and ``PM_BAT_LOW_TIMEOUT`` 5 s), back on battery (0) as soon as it is
  above again; an empty charge is *shut down* (4), for good.
* :class:`LinkModel`: every datagram, either way, is lost with probability ``loss`` and otherwise
  delivered ``latency`` [s] later (plus a uniform jitter up to ``jitter``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

PM_BATTERY, PM_CHARGING, PM_CHARGED, PM_LOW_POWER, PM_SHUTDOWN = 0, 1, 2, 3, 4
"""Power states as ``pm.state`` reports them (firmware ``pm.h`` PMStates)."""


def _check(name: str, value: float, lo: float = 0.0, hi: float = math.inf, open_lo: bool = False) -> None:
    if not math.isfinite(value) or value < lo or value > hi or (open_lo and value == lo):
        raise ValueError(f"{name} = {value!r}: give a finite number in {'(' if open_lo else '['}{lo:g}, {hi:g}]")


@dataclass(frozen=True)
class NoiseConfig:
    sigma_p: float = 0.1
    """Stationary standard deviation of the position estimate's error [m] (per axis)."""
    sigma_v: float = 0.05
    """Stationary standard deviation of the velocity estimate's error [m/s] (per axis)."""
    tau: float = 0.5
    """Correlation time of the errors [s]."""
    seed: int = 0

    def __post_init__(self) -> None:
        _check("sigma_p", self.sigma_p)
        _check("sigma_v", self.sigma_v)
        _check("tau", self.tau, open_lo=True)


class EstimatorNoise:
    """The estimate's error: ``e[k+1] = a e[k] + sigma sqrt(1 - a^2) n[k]`` with ``a = exp(-dt / tau)``
    and ``n`` standard normal, started from its stationary distribution. ``reset()`` (the estimator
    reset of ``kalman.resetEstimation``) draws a fresh error from that distribution."""

    def __init__(self, cfg: NoiseConfig, dt: float) -> None:
        self.cfg = cfg
        self._rng = np.random.default_rng(cfg.seed)
        self._a = math.exp(-dt / cfg.tau)
        self._b = math.sqrt(1.0 - self._a * self._a)
        self._sigma = np.array([cfg.sigma_p] * 3 + [cfg.sigma_v] * 3)
        self.error = np.zeros(6)
        self.reset()

    def reset(self) -> None:
        self.error = self._sigma * self._rng.standard_normal(6)

    def step(self) -> None:
        self.error = self._a * self.error + self._b * self._sigma * self._rng.standard_normal(6)

    @property
    def position(self) -> np.ndarray:
        return self.error[:3]

    @property
    def velocity(self) -> np.ndarray:
        return self.error[3:]


@dataclass(frozen=True)
class BatteryConfig:
    capacity_mah: float = 250.0
    """Charge when full [mAh] (the Crazyflie 2.1's battery)."""
    v_full: float = 4.2
    v_empty: float = 3.0
    v_low: float = 3.2
    r_internal: float = 0.1
    """Internal resistance [ohm]: the voltage sags by ``r I`` under load."""
    idle_a: float = 0.05
    """Current with the motors off [A]."""
    hover_a: float = 2.1
    """Motor current at hover thrust [A] (about 7 minutes of hover from 250 mAh)."""
    charge: float = 1.0
    """State of charge at boot (0..1]."""
    low_delay: float = 5.0
    """How long [s] the voltage must stay below ``v_low`` before the state is low power."""

    def __post_init__(self) -> None:
        _check("capacity_mah", self.capacity_mah, open_lo=True)
        _check("charge", self.charge, 0.0, 1.0, open_lo=True)
        for name in ("r_internal", "idle_a", "hover_a", "low_delay"):
            _check(name, getattr(self, name))
        if not self.v_empty < self.v_low < self.v_full:
            raise ValueError(f"battery voltages: need v_empty < v_low < v_full, got "
                             f"{self.v_empty}, {self.v_low}, {self.v_full}")


class Battery:
    """Charge drained by the motors; :meth:`step` once per control period with the collective
    thrust [N] and the hover thrust [N]."""

    def __init__(self, cfg: BatteryConfig) -> None:
        self.cfg = cfg
        self.charge = cfg.charge
        self.current = cfg.idle_a
        self.state = PM_BATTERY
        self._low_for = 0.0
        """How long [s] the voltage has been below ``v_low``."""

    def step(self, thrust: float, hover_thrust: float, dt: float) -> None:
        c = self.cfg
        ratio = max(0.0, thrust) / hover_thrust if hover_thrust > 0 else 0.0
        self.current = c.idle_a + c.hover_a * ratio ** 1.5
        self.charge = max(0.0, self.charge - self.current * dt / (c.capacity_mah * 3.6))
        self._low_for = self._low_for + dt if self.vbat < c.v_low else 0.0
        if self.charge <= 0.0 or self.state == PM_SHUTDOWN:
            self.state = PM_SHUTDOWN
        elif self._low_for >= c.low_delay:
            self.state = PM_LOW_POWER
        else:
            self.state = PM_BATTERY

    @property
    def open_circuit(self) -> float:
        c = self.cfg
        return c.v_empty + (c.v_full - c.v_empty) * self.charge

    @property
    def vbat(self) -> float:
        return self.open_circuit - self.cfg.r_internal * self.current

    @property
    def level(self) -> float:
        """Charge [%]."""
        return 100.0 * self.charge


@dataclass(frozen=True)
class LinkConfig:
    latency: float = 0.0
    """One-way delay [s] of every datagram, either way."""
    jitter: float = 0.0
    """Extra delay, uniform in [0, jitter] [s]."""
    loss: float = 0.0
    """Probability that a datagram is lost, either way."""
    seed: int = 0

    def __post_init__(self) -> None:
        _check("latency", self.latency, 0.0, 5.0)
        _check("jitter", self.jitter, 0.0, 5.0)
        _check("loss", self.loss, 0.0, 1.0)

    @property
    def active(self) -> bool:
        return self.latency > 0.0 or self.jitter > 0.0 or self.loss > 0.0


class LinkModel:
    """Decides, datagram by datagram, whether it is lost and how late it arrives. Returns ``None``
    for a lost datagram, else the delay [s]."""

    def __init__(self, cfg: LinkConfig) -> None:
        self.cfg = cfg
        self._rng = np.random.default_rng(cfg.seed)
        self.lost = 0
        self.passed = 0

    def decide(self) -> float | None:
        c = self.cfg
        u, j = self._rng.random(2)
        if u < c.loss:
            self.lost += 1
            return None
        self.passed += 1
        return c.latency + c.jitter * float(j)


UP, DOWN = 0, 1
"""The two ways of a radio link: from the ground (cflib) to the vehicle, and back."""


@dataclass(frozen=True)
class RadioConfig:
    """A Crazyradio-like link (``--radio``): one simulated dongle carries every vehicle on it.

    A packet is transmitted in attempts, one ``1 / rate`` airtime slot each, on the dongle's shared
    airtime of its way (uplink and downlink each carry ``rate`` slots a second: on a real Crazyradio a
    downlink packet rides on the acknowledgement of an uplink one, so the two ways run side by side);
    an attempt is lost with probability ``loss`` and retried, up to ``retries`` times (the nRF24's
    automatic retransmission; the Crazyradio's default is 3), after which the packet is lost and
    counted. A packet that would wait more than ``queue`` [s] for airtime is dropped and counted (a
    full queue). Packets of one vehicle and one way arrive in the order they were sent, ``latency``
    (plus a uniform jitter up to ``jitter``) after their last attempt ends: jitter delays, never
    reorders, as on a radio."""

    rate: float = 1000.0
    """Attempts per second the dongle's airtime carries, each way [1/s] (a Crazyradio PA at 2 Mbit/s
    with cflib is of this order; give the figure measured on your own dongle)."""
    retries: int = 3
    """Retransmissions of a packet whose attempt was lost, before it counts as lost."""
    loss: float = 0.0
    """Probability that one attempt (the packet or its acknowledgement) is lost."""
    latency: float = 0.0
    """Delay [s] from the end of the successful attempt to delivery (USB and host scheduling)."""
    jitter: float = 0.0
    """Extra delay, uniform in [0, jitter] [s]; never reorders."""
    queue: float = 0.1
    """Longest wait for airtime [s] before a packet is dropped."""
    degrade: tuple[tuple[float, float], ...] = ()
    """Steps ``(t, loss)``, in time order: from ``t`` [s, on the caller's clock] on, attempts are lost
    with probability ``loss`` instead (a vehicle flying out of range, a crowded channel)."""
    seed: int = 0

    def __post_init__(self) -> None:
        _check("rate", self.rate, open_lo=True)
        _check("loss", self.loss, 0.0, 1.0)
        _check("latency", self.latency, 0.0, 5.0)
        _check("jitter", self.jitter, 0.0, 5.0)
        _check("queue", self.queue, 0.0, 5.0)
        if not (isinstance(self.retries, int) and 0 <= self.retries <= 15):
            raise ValueError(f"retries = {self.retries!r}: give a whole number in [0, 15] (the nRF24's limit)")
        for t, p in self.degrade:
            _check("degrade time", t)
            _check("degrade loss", p, 0.0, 1.0)
        if [t for t, _ in self.degrade] != sorted(t for t, _ in self.degrade):
            raise ValueError(f"degrade = {self.degrade!r}: give the steps in time order")

    def loss_at(self, now: float) -> float:
        """Probability [0..1] that an attempt at ``now`` [s] is lost."""
        loss = self.loss
        for t, p in self.degrade:
            if now >= t:
                loss = p
        return loss


@dataclass
class RadioCounts:
    """What one simulated dongle did, per way (index :data:`UP` or :data:`DOWN`)."""

    sent: list[int] = field(default_factory=lambda: [0, 0])
    """Packets delivered."""
    attempts: list[int] = field(default_factory=lambda: [0, 0])
    """Attempts made (each one slot of airtime)."""
    lost: list[int] = field(default_factory=lambda: [0, 0])
    """Packets lost after every retry."""
    overflow: list[int] = field(default_factory=lambda: [0, 0])
    """Packets dropped because the queue for airtime was full."""


class Radio:
    """One simulated dongle's airtime and losses, shared by its vehicles (see :class:`RadioConfig`).
    Pure: the caller gives the time, a seeded generator draws the losses."""

    def __init__(self, cfg: RadioConfig) -> None:
        self.cfg = cfg
        self._rng = np.random.default_rng(cfg.seed)
        self._free = [-math.inf, -math.inf]
        """When each way's airtime is next free [s]."""
        self.counts = RadioCounts()

    def transmit(self, now: float, way: int, after: float = -math.inf) -> float | None:
        """Send one packet at ``now`` [s] on ``way``; returns when it arrives [s], never before
        ``after`` (the arrival of the same stream's previous packet), or ``None`` if it is lost."""
        c, n = self.cfg, self.counts
        start = max(now, self._free[way])
        if start - now > c.queue:
            n.overflow[way] += 1
            return None
        loss = c.loss_at(now)
        tries, delivered = 0, False
        while not delivered and tries <= c.retries:
            tries += 1
            delivered = self._rng.random() >= loss
        self._free[way] = start + tries / c.rate
        n.attempts[way] += tries
        if not delivered:
            n.lost[way] += 1
            return None
        n.sent[way] += 1
        return max(after, self._free[way] + c.latency + c.jitter * float(self._rng.random()))
