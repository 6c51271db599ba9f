"""tether.transport against real Zenoh sessions on loopback.

Every session has multicast scouting off and explicit ``tcp/127.0.0.1:<port>`` endpoints on ports
picked free at run time, so tests never see each other or the network. Every wait is on a condition
with a timeout; a subprocess holding a token is started with ``subprocess`` (never a fork of this
process, which has Zenoh loaded) and killed with SIGKILL.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import random
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import zenoh

from tether import transport as tp
import msgspec

from tether import wire
from tether.gate import Health
from tether.handoff import PER_TICK, BoundedFifo, InputQueue, LatestSlot, Wakeup
from tether.inputs import Source
from tether.transport import Received, SettingsError, TokenEvent, ZenohSettings

WAIT = 5.0
"""Upper bound [s] on any wait for something that takes milliseconds on loopback."""

REPO = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- helpers
def listener(mode: str = "peer", **kw: object) -> ZenohSettings:
    """Settings that listen on a fresh loopback port. No scouting delay: nothing to wait for."""
    kw.setdefault("scouting_delay", 0.0)
    return ZenohSettings(mode=mode, listen=(tp.loopback_endpoint(tp.free_tcp_port()),), **kw)  # type: ignore[arg-type]


def dialer(target: ZenohSettings, mode: str = "peer", **kw: object) -> ZenohSettings:
    """Settings that connect to ``target``'s listener and listen nowhere (Zenoh's default scouting delay)."""
    return ZenohSettings(mode=mode, connect=target.listen, **kw)  # type: ignore[arg-type]


async def receive_one(publisher: zenoh.Publisher, slot: LatestSlot[Received], wakeup: Wakeup, payload: bytes) -> Received:
    """Wait until the subscriber matches, put ``payload`` once, and wait for it to arrive."""
    await tp.wait_for_subscribers(publisher, WAIT)
    publisher.put(payload)
    async with asyncio.timeout(WAIT):
        while (got := slot.take()) is None:
            await wakeup.wait()
    return got


async def next_event(events: BoundedFifo[TokenEvent], wakeup: Wakeup) -> TokenEvent:
    async with asyncio.timeout(WAIT):
        while (ev := events.pop()) is None:
            await wakeup.wait()
    return ev


@contextlib.asynccontextmanager
async def sessions(*settings: ZenohSettings) -> AsyncIterator[list[zenoh.Session]]:
    """Open sessions in order (listeners before dialers), close them all in reverse."""
    async with contextlib.AsyncExitStack() as stack:
        yield [await stack.enter_async_context(tp.open_session(s)) for s in settings]


# --------------------------------------------------------------------------- pub/sub
@pytest.mark.asyncio
async def test_pubsub_roundtrip_peer_to_peer() -> None:
    a = listener(lease=1.0)
    b = dialer(a, lease=1.0)
    async with sessions(a, b) as (sa, sb):
        wakeup = Wakeup()
        slot: LatestSlot[Received] = LatestSlot(wakeup)
        with (
            tp.declare_subscriber(sa, "tether/test/agent/1/state", slot),
            tp.declare_publisher(sb, "tether/test/agent/1/state", tp.STATE) as pub,
        ):
            got = await receive_one(pub, slot, wakeup, b"x" * 200)
    assert got == Received("tether/test/agent/1/state", b"x" * 200)
    assert slot.overwritten == 0


@pytest.mark.asyncio
async def test_client_router_client_through_python_router() -> None:
    router = listener("router")
    c1 = dialer(router, "client")
    c2 = dialer(router, "client")
    async with sessions(router, c1, c2) as (sr, s1, s2):
        assert [str(z) for z in s1.info.routers_zid()] == [str(sr.zid())]
        assert s1.info.peers_zid() == [] and s2.info.peers_zid() == []  # clients only see the router
        wakeup = Wakeup()
        slot: LatestSlot[Received] = LatestSlot(wakeup)
        with (
            tp.declare_subscriber(s1, "tether/test/plant/*/state", slot),
            tp.declare_publisher(s2, "tether/test/plant/2/state", tp.STATE) as pub,
        ):
            got = await receive_one(pub, slot, wakeup, b"via-router")
    assert got == Received("tether/test/plant/2/state", b"via-router")


@pytest.mark.asyncio
async def test_client_waits_for_a_late_router_within_connect_timeout() -> None:
    router = listener("router")
    scope = tp.open_session(dialer(router, "client", connect_timeout=WAIT))
    opening = asyncio.create_task(scope.__aenter__())
    try:
        await asyncio.sleep(0.2)  # the scenario itself: the router starts late
        assert not opening.done()  # the client is still dialling, not failed
        async with tp.open_session(router) as sr:
            sc = await asyncio.wait_for(opening, WAIT)
            assert [str(z) for z in sc.info.routers_zid()] == [str(sr.zid())]
    finally:
        if not opening.done():
            opening.cancel()
        await scope.__aexit__(None, None, None)


@pytest.mark.asyncio
async def test_publisher_qos_reaches_the_subscriber() -> None:
    a = listener()
    b = dialer(a)
    async with sessions(a, b) as (sa, sb):
        box: BoundedFifo[zenoh.Sample] = BoundedFifo(4, wakeup := Wakeup())
        with (
            sa.declare_subscriber("tether/test/qos", box.put),
            tp.declare_publisher(sb, "tether/test/qos", tp.COMMAND) as pub,
        ):
            assert pub.congestion_control == zenoh.CongestionControl.DROP
            assert pub.priority == zenoh.Priority.REAL_TIME
            await tp.wait_for_subscribers(pub, WAIT)
            pub.put(b"u")
            async with asyncio.timeout(WAIT):
                while (sample := box.pop()) is None:
                    await wakeup.wait()
    assert sample.priority == zenoh.Priority.REAL_TIME
    assert sample.congestion_control == zenoh.CongestionControl.DROP
    assert sample.express is True


@pytest.mark.asyncio
async def test_a_routers_ingress_limit_passes_a_flood_at_its_rate_at_most() -> None:
    """Real time, a router limits each link's ingress on a stream key to ``LIMIT_FACTOR`` times the
    mission's rate (``deploy/localtls.py``, Zenoh's ``downsampling``, one sample per window of
    ``1 / freq``): a session flooding the key reaches a subscriber at that rate at most, however fast it
    puts. (Whether a run's own bursts pass is measured, not timed here: ``bench/lost_samples.py``.)"""
    from deploy import localtls

    freq = localtls.LIMIT_FACTOR * 50.0
    key = "tether/test/limited"
    r = listener("router", ingress_limits=((key, freq),))
    pub_s, sub_s = dialer(r, "client"), dialer(r, "client")
    arrivals: list[float] = []
    async with sessions(r, pub_s, sub_s) as (_, sp, ss):
        with (ss.declare_subscriber(key, lambda _s: arrivals.append(time.monotonic())),
              tp.declare_publisher(sp, key, tp.STATE) as pub):
            await tp.wait_for_subscribers(pub, WAIT)
            t0 = time.monotonic()
            sent = 30_000
            for _ in range(sent):
                pub.put(b"junk")
            took = time.monotonic() - t0
            # until the arrivals stop (none for 0.3 s), WAIT at most
            async with asyncio.timeout(WAIT):
                while not arrivals or time.monotonic() - arrivals[-1] < 0.3:
                    await asyncio.sleep(0.05)
    assert took * freq < sent / 2, f"the flood was too slow to test the limit: {sent} puts in {took:.3f} s"
    span = arrivals[-1] - t0  # the router's windows lie within it
    assert 1 <= len(arrivals) <= 1.1 * freq * span + 2, (len(arrivals), span, freq)


@pytest.mark.asyncio
async def test_wait_for_subscribers_times_out_without_one() -> None:
    async with tp.open_session(listener()) as s:
        with tp.declare_publisher(s, "tether/test/nobody") as pub:
            with pytest.raises(TimeoutError, match="tether/test/nobody"):
                await tp.wait_for_subscribers(pub, 0.2)


# --------------------------------------------------------------------------- sinks
def test_latest_slot_keeps_only_the_newest_and_counts_overwrites() -> None:
    slot: LatestSlot[int] = LatestSlot()
    assert slot.take() is None and slot.peek() is None and not slot.fresh
    for v in (1, 2, 3):
        slot.put(v)
    assert slot.fresh
    assert slot.take() == 3
    assert slot.overwritten == 2
    assert slot.take() is None  # nothing new since
    assert slot.peek() == 3  # but the newest is still held
    slot.put(4)
    assert slot.take() == 4
    assert (slot.written, slot.taken, slot.overwritten) == (4, 2, 2)


def test_latest_slot_accounts_for_every_value_under_concurrency() -> None:
    slot: LatestSlot[int] = LatestSlot()
    n = 20_000
    seen: list[int] = []
    done = threading.Event()

    def writer() -> None:
        for i in range(n):
            slot.put(i)
        done.set()

    t = threading.Thread(target=writer)
    t.start()
    while not done.is_set() or slot.fresh:
        v = slot.take()
        if v is not None:
            seen.append(v)
    t.join()
    assert seen == sorted(seen) and len(set(seen)) == len(seen)  # newest only: never goes back
    assert seen[-1] == n - 1
    assert slot.written == n == slot.taken + slot.overwritten


def test_bounded_fifo_drops_the_oldest_and_counts() -> None:
    q: BoundedFifo[int] = BoundedFifo(3)
    for i in range(5):
        q.put(i)
    assert len(q) == 3 and q.dropped == 2
    assert q.pop() == 2
    assert q.drain() == [3, 4]
    assert q.pop() is None
    assert q.written == q.popped + q.dropped + len(q) == 5
    with pytest.raises(ValueError, match="capacity"):
        BoundedFifo(0)


def test_an_input_queue_admits_the_first_two_of_a_tick_and_drops_the_rest_as_they_come() -> None:
    q: InputQueue[tuple[int, str]] = InputQueue(3, tick_of=lambda item: item[0])
    for item in [(1, "genuine"), (1, "forged"), (1, "again"), (1, "again"), (2, "genuine"), (3, "genuine"),
                 (4, "genuine")]:
        q.put(item)
    assert q.excess == 2 and q.dropped == 2  # tick 1's third and fourth; then the oldest two, to make room
    assert q.take(8) == [(2, "genuine"), (3, "genuine"), (4, "genuine")]
    assert q.written == q.popped + q.dropped + q.excess + len(q) == 7
    q.put((9, "no tick"))
    untimed: InputQueue[int] = InputQueue(2)  # without tick_of: drop-oldest alone
    for i in range(4):
        untimed.put(i)
    assert untimed.take(8) == [2, 3] and untimed.excess == 0 and untimed.dropped == 2


FLOOD = 30
"""Forged copies a flooding publisher sends after each genuine sample."""


async def flooded(queue: InputQueue[Received] | BoundedFifo[Received], ticks: int) -> tuple[Source, int]:
    """A real Zenoh publisher on loopback sends, each tick, the genuine ``agent/1/state`` sample, then
    :data:`FLOOD` forged copies of it (mode HOLD, each under its own number) on the same key; the reader
    decodes at most 8 queued samples a tick (an agent's budget) into a judged source, after the whole
    tick's flood has arrived (the worst case: a reader that falls behind). Returns the source and the
    samples the queue took in."""
    key = "tether/flood/agent/1/state"
    a = listener(lease=1.0)
    b = dialer(a, lease=1.0)
    src = Source(key, wire.State, 1, health=Health(window=50, share=0.5))
    receiver = wire.Receiver(2)
    every = tp.StreamQos(zenoh.Priority.DATA, zenoh.CongestionControl.BLOCK, express=False)  # none lost on the way
    async with sessions(a, b) as (sa, sb):
        with (
            tp.declare_subscriber(sa, key, queue),
            tp.declare_publisher(sb, key, every) as pub,
        ):
            await tp.wait_for_subscribers(pub, WAIT)
            sent = 0
            for k in range(ticks):
                genuine = wire.State(sender=1, seq=k * (FLOOD + 1), k=k, t=0.01 * k, p=[0.1 * k, 0.0],
                                     vel=[10.0, 0.0], a=[0.0, 0.0])
                pub.put(wire.encode(genuine))
                for c in range(FLOOD):
                    pub.put(wire.encode(msgspec.structs.replace(genuine, seq=genuine.seq + 1 + c, mode=wire.HOLD)))
                sent += 1 + FLOOD
                async with asyncio.timeout(WAIT):
                    while queue.written < sent:
                        await asyncio.sleep(0.001)
                items = queue.take(8) if isinstance(queue, InputQueue) else queue.drain()[-8:]
                for rec in items:
                    msg = receiver.accept(rec.payload, wire.State, 1)
                    if msg is not None:
                        src.offer(msg)
    return src, sent


@pytest.mark.asyncio
async def test_a_flood_of_forged_copies_on_a_real_key_never_evicts_the_genuine_sample() -> None:
    """Each tick's genuine sample is decoded and held (the first of its tick), each tick's first forged
    copy is a conflict and contests it, and the rest of the flood is dropped as it comes, counted:
    bounded (8 queued at most). Against drop-oldest (the queue before), the genuine samples were
    evicted before they were decoded and forged ones held unchallenged."""
    ticks = 20
    queue: InputQueue[Received] = InputQueue(8, tick_of=tp.tick_of)
    src, sent = await flooded(queue, ticks)
    assert all(src.by_tick[k].mode == wire.FLYING and src.by_tick[k].seq == k * (FLOOD + 1) for k in range(ticks))
    assert src.conflicts == ticks * (PER_TICK - 1) and sorted(src.contested) == list(range(ticks))
    assert queue.excess == ticks * (FLOOD + 1 - PER_TICK) and queue.dropped == 0 and len(queue) == 0
    assert queue.written == sent == queue.popped + queue.excess
    assert src.health is not None and src.health.suspect  # 40 bad verdicts of 60
    old: BoundedFifo[Received] = BoundedFifo(8)  # drop-oldest: what the queue did before
    src, _ = await flooded(old, ticks)
    print(f"drop-oldest: {sum(m.mode == wire.FLYING for m in src.by_tick.values())} of {ticks} genuine held, "
          f"{src.conflicts} conflicts; first two of each tick: {ticks} held, {ticks} conflicts")
    assert not any(m.mode == wire.FLYING for m in src.by_tick.values())


@pytest.mark.asyncio
async def test_wakeup_from_another_thread_coalesces() -> None:
    wakeup = Wakeup()
    slot: LatestSlot[int] = LatestSlot(wakeup)
    assert not await wakeup.wait(timeout=0.01)
    t = threading.Thread(target=lambda: [slot.put(i) for i in range(100)])
    t.start()
    assert await wakeup.wait(timeout=WAIT)
    last = slot.take()
    t.join()
    if slot.fresh:  # a put after that take found no wake-up pending, so it armed a new one
        assert await wakeup.wait(timeout=WAIT)
        last = slot.take()
    assert last == 99
    assert slot.taken + slot.overwritten == 100
    assert not await wakeup.wait(timeout=0.01)  # nothing left: no spurious wake-up


# --------------------------------------------------------------------------- liveliness
@pytest.mark.asyncio
async def test_token_appears_then_goes_when_its_session_closes() -> None:
    a = listener(lease=1.0)
    b = dialer(a, lease=1.0)
    key = tp.token_key("test", "agent", 1)
    async with tp.open_session(a) as sa:
        holder = tp.open_session(b)
        sb = await holder.__aenter__()
        try:
            token = tp.declare_token(sb, key)  # keep a reference: a dropped token is undeclared
            await tp.wait_for_tokens(sa, [key], WAIT)
            wakeup = Wakeup()
            events: BoundedFifo[TokenEvent] = BoundedFifo(16, wakeup)
            with tp.watch_tokens(sa, "@tether/test/**", events):
                assert await next_event(events, wakeup) == TokenEvent(key, True)  # history: already there
                await holder.__aexit__(None, None, None)  # close the session, token still declared
                assert await next_event(events, wakeup) == TokenEvent(key, False)
                del token
        finally:
            await holder.__aexit__(None, None, None)


@pytest.mark.asyncio
async def test_wildcards_do_not_match_the_hermetic_token_root() -> None:
    a = listener()
    async with sessions(a, dialer(a)) as (sa, sb):
        key = tp.token_key("test", "leader", 0)
        with tp.declare_token(sb, key):
            await tp.wait_for_tokens(sa, [key], WAIT)
            wakeup = Wakeup()
            stray: BoundedFifo[TokenEvent] = BoundedFifo(4, wakeup)
            named: BoundedFifo[TokenEvent] = BoundedFifo(4, wakeup)
            with tp.watch_tokens(sa, "**", stray), tp.watch_tokens(sa, "@tether/*/leader/*", named):
                assert await next_event(named, wakeup) == TokenEvent(key, True)  # from history
                later = tp.token_key("test", "leader", 1)
                with tp.declare_token(sb, later):
                    assert await next_event(named, wakeup) == TokenEvent(later, True)  # live
                assert await next_event(named, wakeup) == TokenEvent(later, False)
                assert len(stray) == 0


@pytest.mark.asyncio
async def test_wait_for_tokens_names_the_missing_ones() -> None:
    a = listener()
    present = tp.token_key("test", "agent", 1)
    absent = [tp.token_key("test", "agent", 2), tp.token_key("test", "plant", 2)]
    async with sessions(a, dialer(a)) as (sa, sb):
        with tp.declare_token(sb, present):
            with pytest.raises(tp.TokensMissing) as err:
                await tp.wait_for_tokens(sa, [present, *absent], 0.3)
    assert err.value.missing == sorted(absent)
    assert all(k in str(err.value) for k in absent) and present not in str(err.value)


HOLDER = textwrap.dedent(
    """
    import sys, time
    from tether import transport as tp
    settings = tp.ZenohSettings(connect=(sys.argv[1],), lease=1.0)
    with tp.open_session(settings) as session, tp.declare_token(session, sys.argv[2]):
        print("ready", flush=True)
        time.sleep(60)  # until killed
    """
)


@pytest.mark.asyncio
async def test_token_goes_when_its_process_is_killed() -> None:
    a = listener(lease=1.0)
    key = tp.token_key("test", "agent", 7)
    async with tp.open_session(a) as sa:
        wakeup = Wakeup()
        events: BoundedFifo[TokenEvent] = BoundedFifo(16, wakeup)
        with tp.watch_tokens(sa, "@tether/test/**", events):
            proc = subprocess.Popen(
                [sys.executable, "-c", HOLDER, a.listen[0], key],
                cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True,
            )
            try:
                assert await next_event(events, wakeup) == TokenEvent(key, True)
                proc.send_signal(signal.SIGKILL)
                assert await next_event(events, wakeup) == TokenEvent(key, False)
                assert await asyncio.to_thread(proc.wait, WAIT) == -signal.SIGKILL
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait(WAIT)
                if proc.stderr is not None:
                    proc.stderr.close()


# --------------------------------------------------------------------------- settings
def test_config_carries_the_verified_keys() -> None:
    s = ZenohSettings(
        mode="peer", listen=("tcp/127.0.0.1:0",), connect=("tcp/127.0.0.1:7447",),
        lease=1.5, keep_alive=3, scouting_delay=0.25, connect_timeout=2.0,
        tls=tp.TlsFiles(root_ca_certificate="/etc/tether/ca.pem"),
    )
    c = tp.zenoh_config(s)
    assert c.get_json("mode") == '"peer"'
    assert c.get_json("listen/endpoints") == '["tcp/127.0.0.1:0"]'
    assert c.get_json("connect/endpoints") == '["tcp/127.0.0.1:7447"]'
    assert c.get_json("scouting/multicast/enabled") == "false"
    assert c.get_json("scouting/gossip/enabled") == "true"
    assert '"to_peer":"greater-zid"' in c.get_json("scouting/gossip/autoconnect_strategy")
    assert c.get_json("transport/link/tx/lease") == "1500"
    assert c.get_json("transport/link/tx/keep_alive") == "3"
    assert c.get_json("scouting/delay") == "250"
    assert c.get_json("connect/timeout_ms") == "2000"
    assert c.get_json("transport/link/tls/root_ca_certificate") == '"/etc/tether/ca.pem"'


def test_a_router_queues_bursts_of_the_streams_and_a_client_keeps_zenohs_queue() -> None:
    """A router's links to a process that hears many streams (the recorder hears every plant, all
    publishing at the same phase) must hold one tick's burst of express samples: :data:`ROUTER_TX_QUEUE`."""
    router = tp.zenoh_config(ZenohSettings(mode="router", listen=("tcp/127.0.0.1:0",)))
    size = json.loads(router.get_json("transport/link/tx/queue/size"))
    assert size == tp.ROUTER_TX_QUEUE
    assert size["interactive_high"] == size["real_time"] == size["data_low"] == 16  # the streams' priorities
    assert [tp.STATE.priority, tp.COMMAND.priority, tp.TELEMETRY.priority] == [
        zenoh.Priority.INTERACTIVE_HIGH, zenoh.Priority.REAL_TIME, zenoh.Priority.DATA_LOW]
    client = tp.zenoh_config(ZenohSettings(mode="client", connect=("tcp/127.0.0.1:7447",)))
    assert json.loads(client.get_json("transport/link/tx/queue/size"))["interactive_high"] == 2  # Zenoh's


@pytest.mark.parametrize(
    ("settings", "field"),
    [
        (ZenohSettings(mode="banana", listen=("tcp/127.0.0.1:0",)), "mode"),  # type: ignore[arg-type]
        (ZenohSettings(listen=("nonsense",)), "listen[0]"),
        (ZenohSettings(listen=("zzz/127.0.0.1:7447",)), "listen[0]"),
        (ZenohSettings(listen=("tcp/127.0.0.1",)), "listen[0]"),
        (ZenohSettings(connect=("tcp/127.0.0.1:99999",)), "connect[0]"),
        (ZenohSettings(connect=("tcp/127.0.0.1:0",)), "connect[0]"),
        (ZenohSettings(connect="tcp/127.0.0.1:7447"), "connect"),  # type: ignore[arg-type]
        (ZenohSettings(mode="client"), "connect"),
        (ZenohSettings(mode="client", connect=("tcp/127.0.0.1:7447",), listen=("tcp/127.0.0.1:0",)), "listen"),
        (ZenohSettings(mode="router"), "listen"),
        (ZenohSettings(), "listen"),
        (ZenohSettings(listen=("tcp/127.0.0.1:0",), lease=0.0), "lease"),
        (ZenohSettings(listen=("tcp/127.0.0.1:0",), lease=-1.0), "lease"),
        (ZenohSettings(listen=("tcp/127.0.0.1:0",), lease=float("nan")), "lease"),
        (ZenohSettings(listen=("tcp/127.0.0.1:0",), keep_alive=0), "keep_alive"),
        (ZenohSettings(listen=("tcp/127.0.0.1:0",), connect_timeout=0.0), "connect_timeout"),
        (ZenohSettings(listen=("tcp/127.0.0.1:0",), scouting_delay=-0.1), "scouting_delay"),
        (ZenohSettings(listen=("tcp/127.0.0.1:0",), tls=tp.TlsFiles(listen_certificate="c.pem")),
         "tls.listen_certificate"),
    ],
)
def test_config_rejects_bad_settings_naming_the_field(settings: ZenohSettings, field: str) -> None:
    with pytest.raises(SettingsError) as err:
        tp.zenoh_config(settings)
    assert field in [f for f, _ in err.value.problems]
    assert f"  {field}: " in str(err.value)
    with pytest.raises(SettingsError):
        tp.open_session(settings)  # nothing is opened for invalid settings


@pytest.mark.parametrize(
    ("raw", "field"),
    [
        ({"mode": "peer", "listen": ["tcp/127.0.0.1:0"], "leese": 1.0}, "leese"),
        ({"mode": "peer", "listen": ["tcp/127.0.0.1:0"], "lease": "1s"}, "lease"),
        ({"mode": "peer", "listen": ["tcp/127.0.0.1:0"], "multicast_scouting": "yes"}, "multicast_scouting"),
        ({"mode": "peer", "listen": ["tcp/127.0.0.1:0"], "lease": -2}, "lease"),
    ],
)
def test_load_settings_rejects_bad_tables_naming_the_field(raw: dict[str, object], field: str) -> None:
    with pytest.raises(SettingsError) as err:
        tp.load_settings(raw)
    assert [f for f, _ in err.value.problems] == [field]


def test_load_settings_accepts_a_table() -> None:
    s = tp.load_settings({"mode": "client", "connect": ["tcp/127.0.0.1:7447"], "lease": 1})
    assert s == ZenohSettings(mode="client", connect=("tcp/127.0.0.1:7447",), lease=1.0)


def test_opening_on_a_busy_port_says_so() -> None:
    s = listener()
    with tp.open_session(s):
        with pytest.raises(tp.TransportError, match="Address already in use"):
            with tp.open_session(s):
                pass


def test_free_tcp_port_is_bindable_and_below_the_ephemeral_range() -> None:
    ports = {tp.free_tcp_port() for _ in range(20)}
    assert len(ports) > 1
    for p in ports:
        assert 1024 <= p <= 65535
        assert tp.loopback_endpoint(p) == f"tcp/127.0.0.1:{p}"


def test_free_tcp_port_never_gives_a_port_twice_even_when_the_generator_repeats_itself() -> None:
    """A port is free until somebody binds it, so two picks in a row could return the same one (a
    deployment test once gave an agent the leader's port): a port given out is never given again,
    even by a generator that draws the same numbers (two of them seeded alike), nor inside a span."""
    first = [tp.free_tcp_port(random.Random(7)) for _ in range(5)]
    again = [tp.free_tcp_port(random.Random(7)) for _ in range(5)]
    assert len(set(first + again)) == 10
    p = tp.free_tcp_port(random.Random(7), span=3)
    assert not {p, p + 1, p + 2} & set(first + again)
    for q in (p, p + 1, p + 2):
        with socket.socket() as s:
            s.bind(("127.0.0.1", q))  # free: nothing bound it


def test_a_port_the_user_named_is_never_picked_before_its_session_binds_it() -> None:
    """``tether run --listen tcp/127.0.0.1:P`` names a port that stays free until the router binds
    it; the launcher's own router port is picked in between and once picked P (the launcher then
    refused its own listen list). A reserved port is never returned, even when it is drawn first."""
    low = tp.free_tcp_port()
    named = [tp.loopback_endpoint(low + 1), f"tls/[::1]:{low + 2}#iface=lo", "unixsock-stream/x.sock"]
    assert [tp.endpoint_port(e) for e in named] == [low + 1, low + 2, None]

    class Draws(random.Random):  # draws the named ports first, then ones nobody named
        def __init__(self, ports: list[int]) -> None:
            super().__init__(0)
            self.ports = ports

        def randint(self, a: int, b: int) -> int:
            return self.ports.pop(0)

    tp.reserve_ports(named)
    assert tp.free_tcp_port(Draws([low + 1, low + 2, *range(low + 3, low + 40)])) in range(low + 3, low + 40)


def test_token_key_is_hermetic_and_rejects_bad_chunks() -> None:
    assert tp.token_key("sect4", "agent", 3) == "@tether/sect4/agent/3"
    with pytest.raises(ValueError, match="role"):
        tp.token_key("sect4", "ag/ent", 3)
