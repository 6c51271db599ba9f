"""The software Crazyflies' process adapter: one UDP endpoint per vehicle, one 100 Hz ticker for all.

Each vehicle (:class:`plant.cfsim.firmware.Firmware` around a :class:`plant.quadrotor.Quadrotor`)
listens on its own UDP port and answers cflib's ``udp://HOST:PORT`` link: every datagram is one
CRTP packet, answered at once to the address it came from. Log packets go to the vehicle's
*client*, the address that sent it the last packet, while that client has been heard from within
``client_timeout`` (cflib pings ten times a second while it is connected), so that a vanished
client does not keep a stream of log packets going.

Simulated time follows the monotonic clock: one task wakes every 10 ms (a
:class:`tether.clock.RealtimeClock`) and advances every vehicle by one control period, its 500 Hz
attitude loop and 1 kHz rigid-body steps included. A wake-up that comes late runs the ticks it
missed back to back; if it falls more than ``max_lag`` behind (a suspended or starved process), the
missing time is skipped instead and counted in :attr:`Ticker.slips`.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TextIO

import numpy as np

from plant.cfsim import crtp, realism
from plant.cfsim.firmware import PERIOD, Firmware, FirmwareConfig
from plant.quadrotor import Quadrotor, QuadrotorParams
from tether.clock import RealtimeClock

log = logging.getLogger("tether.cfsim")

Address = tuple[str, int]


@dataclass(frozen=True)
class VehicleConfig:
    """One simulated vehicle: its UDP port, where it starts and its firmware settings."""

    port: int
    p0: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Start position [m; world frame, z up]; ``z = 0`` is the floor."""
    yaw0: float = 0.0
    """Start yaw [rad]."""
    firmware: FirmwareConfig = field(default_factory=FirmwareConfig)
    quadrotor: QuadrotorParams | None = None
    """This vehicle's airframe (its mass, say); None: :attr:`SimConfig.quadrotor`, every vehicle's."""


@dataclass(frozen=True)
class SimConfig:
    vehicles: tuple[VehicleConfig, ...]
    host: str = "127.0.0.1"
    """Address every endpoint binds to."""
    quadrotor: QuadrotorParams = field(default_factory=QuadrotorParams)
    client_timeout: float = 2.0
    """Log packets stop [s] after the client was last heard from."""
    max_lag: float = 0.25
    """Largest backlog [s] the ticker catches up on; beyond it simulated time skips."""
    trace: str | None = None
    """File to record every vehicle's true state in, one line per vehicle and tick (see :class:`Ticker`)."""
    link: realism.LinkConfig = field(default_factory=realism.LinkConfig)
    """Latency and loss of every vehicle's link, both ways (vehicle i seeds its link with seed + i)."""
    radio: realism.RadioConfig | None = None
    """A Crazyradio-like link instead of ``link`` (:class:`RadioLink`); None: plain UDP."""
    per_radio: int = 0
    """With ``radio``: vehicles per simulated dongle (vehicle i of the process is on dongle
    ``i // per_radio``, seeded ``seed + dongle``); 0: every vehicle of the process on one."""


class RadioLink:
    """One vehicle's two streams through its simulated dongle (:class:`realism.Radio`, shared with the
    dongle's other vehicles): each datagram waits for airtime and its retries, and arrives in order
    or not at all. Runs in the event loop's thread; a FIFO per way holds what is in the air, so that
    two arrivals due at the same instant still come out in the order they were sent."""

    def __init__(self, radio: realism.Radio, monotonic: Callable[[], float], t0: float) -> None:
        self.radio = radio
        self._monotonic = monotonic
        self._t0 = t0
        self._last = [-math.inf, -math.inf]
        self._air: tuple[deque[Callable[[], None]], deque[Callable[[], None]]] = (deque(), deque())

    def carry(self, way: int, deliver: Callable[[], None]) -> None:
        """Put one datagram on ``way`` (:data:`realism.UP` or :data:`realism.DOWN`); ``deliver`` is
        called when it arrives, never if it is lost. Returns at once."""
        now = self._monotonic() - self._t0
        at = self.radio.transmit(now, way, self._last[way])
        if at is None:
            return
        self._last[way] = at
        self._air[way].append(deliver)
        asyncio.get_running_loop().call_later(max(0.0, at - now), self._land, way)

    def _land(self, way: int) -> None:
        self._air[way].popleft()()


class Endpoint(asyncio.DatagramProtocol):
    """One vehicle's UDP endpoint. Datagrams are handled in the event loop's thread, in order."""

    def __init__(self, fw: Firmware, client_timeout: float, monotonic: Callable[[], float],
                 link: realism.LinkConfig | None = None, radio: RadioLink | None = None) -> None:
        self.fw = fw
        self._radio = radio
        self._link_in = realism.LinkModel(link) if link is not None and link.active else None
        self._link_out = (realism.LinkModel(realism.LinkConfig(link.latency, link.jitter, link.loss, link.seed + 1_000_003))
                          if link is not None and link.active else None)
        self.client: Address | None = None
        self.transport: asyncio.DatagramTransport | None = None
        self._client_timeout = client_timeout
        self._monotonic = monotonic
        self._last_heard = -float("inf")
        self.received = 0
        self.sent = 0

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]  # a datagram transport

    def datagram_received(self, data: bytes, addr: Address) -> None:
        self.received += 1
        if self._radio is not None:
            self._radio.carry(realism.UP, functools.partial(self._receive, data, addr))
            return
        if self._link_in is not None:
            delay = self._link_in.decide()
            if delay is None:
                return
            if delay > 0.0:
                asyncio.get_running_loop().call_later(delay, self._receive, data, addr)
                return
        self._receive(data, addr)

    def _receive(self, data: bytes, addr: Address) -> None:
        try:
            pkt = crtp.decode(data)
        except crtp.CrtpError:
            self.fw.dropped += 1
            return
        if addr != self.client:
            self.fw.console_print(f"CFSIM: vehicle {self.fw.cfg.instance}, link from {addr[0]}:{addr[1]}\n")
        self.client, self._last_heard = addr, self._monotonic()
        for reply in self.fw.handle(pkt):
            self._send(reply, addr)

    def error_received(self, exc: Exception) -> None:
        log.debug("udp error on %s: %s", self.fw.cfg.instance, exc)

    def publish(self, packets: list[crtp.Packet]) -> None:
        """Send ``packets`` to the client, if it is still there."""
        if not packets or self.client is None:
            return
        if self._monotonic() - self._last_heard > self._client_timeout:
            return
        for pk in packets:
            self._send(pk, self.client)

    def _send(self, pkt: crtp.Packet, addr: Address) -> None:
        if self._radio is not None:
            self._radio.carry(realism.DOWN, functools.partial(self._sendto, crtp.encode(pkt), addr))
            return
        if self._link_out is not None:
            delay = self._link_out.decide()
            if delay is None:
                return
            if delay > 0.0:
                asyncio.get_running_loop().call_later(delay, self._sendto, crtp.encode(pkt), addr)
                return
        self._sendto(crtp.encode(pkt), addr)

    def _sendto(self, raw: bytes, addr: Address) -> None:
        if self.transport is None or self.transport.is_closing():
            return
        self.transport.sendto(raw, addr)
        self.sent += 1


@dataclass
class Ticker:
    """Advances every vehicle one control period per tick of a real-time clock."""

    endpoints: list[Endpoint]
    clock: RealtimeClock
    max_lag: float
    k: int = 0
    slips: int = 0
    """How often simulated time skipped ahead because the process fell too far behind."""
    trace: TextIO | None = None
    """Where to record, after each tick, ``k instance x y z vx vy vz thrust supervisor`` per vehicle:
    tick, position [m] and velocity [m/s] (world frame), collective motor thrust [N] and the
    supervisor's state (``plant.cfsim.supervisor.SupState`` value)."""

    async def run(self) -> None:
        """Tick forever (until cancelled)."""
        while True:
            self.k += 1
            late = await self.clock.wait_for(self.k)
            if late > self.max_lag:
                self.clock.start += late
                self.slips += 1
                log.warning("fell %.3f s behind real time; skipped ahead", late)
            for ep in self.endpoints:
                ep.publish(ep.fw.tick())
                if self.trace is not None:
                    fw = ep.fw
                    q = fw.quad
                    self.trace.write(f"{fw.k} {fw.cfg.instance} {' '.join(f'{c:.5f}' for c in (*q.p, *q.v))} "
                                     f"{float(q.motor_thrusts.sum()):.5f} {fw.supervisor_state.value}\n")


def _same(ep: Endpoint) -> Endpoint:
    """The protocol factory of one vehicle's datagram endpoint: always its own ``ep``."""
    return ep


async def run(cfg: SimConfig, monotonic: Callable[[], float] = time.monotonic,
              on_ready: Callable[[list[tuple[int, str]]], None] | None = None) -> None:
    """Serve every vehicle of ``cfg`` until cancelled. ``on_ready`` is called once every endpoint is
    bound, with ``(instance, uri)`` pairs. Raises ``OSError`` if a port cannot be bound (nothing is
    left open then)."""
    loop = asyncio.get_running_loop()
    endpoints: list[Endpoint] = []
    trace: TextIO | None = None
    radios = _radios(cfg)
    t0 = monotonic()
    try:
        for i, v in enumerate(cfg.vehicles):
            quad = Quadrotor(v.quadrotor or cfg.quadrotor, np.array(v.p0, dtype=float), yaw0=v.yaw0)
            link = cfg.link
            if link.active:
                link = realism.LinkConfig(link.latency, link.jitter, link.loss, link.seed + v.firmware.instance)
            radio = None if not radios else RadioLink(radios[i // (cfg.per_radio or len(cfg.vehicles))], monotonic, t0)
            ep = Endpoint(Firmware(quad, v.firmware), cfg.client_timeout, monotonic, None if radio else link, radio)
            await loop.create_datagram_endpoint(functools.partial(_same, ep), local_addr=(cfg.host, v.port))
            endpoints.append(ep)
        if on_ready is not None:
            on_ready([(v.firmware.instance, f"udp://{cfg.host}:{v.port}") for v in cfg.vehicles])
        trace = open(cfg.trace, "w", encoding="utf-8") if cfg.trace else None  # noqa: SIM115 (closed below)
        ticker = Ticker(endpoints, RealtimeClock(PERIOD, monotonic(), monotonic), cfg.max_lag, trace=trace)
        await ticker.run()
    finally:
        for r, dongle in enumerate(radios):
            n = dongle.counts
            log.info("radio %d: up %d sent, %d lost, %d dropped (queue), %d attempts; down %d sent, %d lost, "
                     "%d dropped (queue), %d attempts", r, n.sent[0], n.lost[0], n.overflow[0], n.attempts[0],
                     n.sent[1], n.lost[1], n.overflow[1], n.attempts[1])
        if trace is not None:
            trace.close()
        for ep in endpoints:
            if ep.transport is not None:
                ep.transport.close()


def _radios(cfg: SimConfig) -> list[realism.Radio]:
    """The simulated dongles of ``cfg`` (none without ``radio``), dongle d seeded ``seed + d``."""
    rc = cfg.radio
    if rc is None:
        return []
    per = cfg.per_radio or len(cfg.vehicles)
    count = -(-len(cfg.vehicles) // per)
    return [realism.Radio(dataclasses.replace(rc, seed=rc.seed + d)) for d in range(count)]
