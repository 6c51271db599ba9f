"""Publish-to-callback latency between two processes on loopback, peer-to-peer vs client-router-client.

    .venv/bin/python bench/zenoh_probe.py                 # all four cases, 10 s each (~45 s)
    .venv/bin/python bench/zenoh_probe.py --seconds 3 --topology star --callback indirect

A publisher process puts ``rate`` samples per second of ``size`` bytes on one key with the STATE QoS;
each payload starts with the sender's CLOCK_MONOTONIC time (system-wide on Linux, so comparable across
processes). A subscriber process records, per sample:

- ``callback``: time at the subscriber callback (on Zenoh's thread) minus send time;
- ``loop``: time at which the asyncio task, woken through :class:`tether.handoff.Wakeup`, takes the
  sample from its :class:`LatestSlot`, minus send time: what a control tick would see.

Topologies: ``p2p`` (subscriber peer listens, publisher peer connects) and ``star`` (a router session in
a third process, both ends clients). Callbacks: ``indirect`` (zenoh-python's default: a Python thread per
subscriber fed by a Zenoh channel; what ``tether.transport.declare_subscriber`` uses) and ``direct``
(``zenoh.handlers.Callback(..., indirect=False)``: the callback runs on Zenoh's network thread).
Every process is a fresh interpreter started with ``subprocess`` (no fork of a process with Zenoh loaded).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tether import handoff  # noqa: E402
from tether import transport as tp  # noqa: E402

KEY = "tether/probe/agent/1/state"
HEADER = struct.Struct("<qII")  # send time [ns, CLOCK_MONOTONIC], sequence number, samples in the run


# --------------------------------------------------------------------------- child roles
def run_router(endpoint: str) -> None:
    settings = tp.ZenohSettings(mode="router", listen=(endpoint,), scouting_delay=0.0)
    with tp.open_session(settings):
        print("ready", flush=True)
        sys.stdin.read()  # until the orchestrator closes our stdin


class _Stamp:
    """Sink that stamps the callback time, then hands the sample to a LatestSlot."""

    def __init__(self, slot: handoff.LatestSlot[tuple[int, bytes]], out: list[int]):
        self.slot, self.out = slot, out

    def put(self, item: tp.Received) -> None:
        now = time.monotonic_ns()
        self.out.append(now - HEADER.unpack_from(item.payload)[0])
        self.slot.put((now, item.payload))


async def run_sub(settings: tp.ZenohSettings, callback: str, seconds: float) -> None:
    cb_lat: list[int] = []
    loop_lat: list[int] = []
    seqs: list[int] = []
    async with tp.open_session(settings) as session:
        wakeup = handoff.Wakeup()
        slot: handoff.LatestSlot[tuple[int, bytes]] = handoff.LatestSlot(wakeup)
        stamp = _Stamp(slot, cb_lat)
        if callback == "indirect":
            sub = tp.declare_subscriber(session, KEY, stamp)
        else:
            import zenoh

            def on_sample(s: zenoh.Sample) -> None:
                stamp.put(tp.Received(str(s.key_expr), s.payload.to_bytes()))

            sub = session.declare_subscriber(KEY, zenoh.handlers.Callback(on_sample, indirect=False))
        print("ready", flush=True)
        cpu0 = wall0 = None
        n_expected = None
        try:
            async with asyncio.timeout(seconds + 15):
                while True:
                    await wakeup.wait()
                    got = slot.take()
                    if got is None:
                        continue
                    now = time.monotonic_ns()
                    t_send, seq, n = HEADER.unpack_from(got[1])
                    if cpu0 is None:
                        cpu0, wall0, n_expected = time.process_time(), time.monotonic(), n
                    loop_lat.append(now - t_send)
                    seqs.append(seq)
                    if seq == n - 1:
                        break
        except TimeoutError:
            pass
        cpu = (time.process_time() - cpu0) if cpu0 is not None else float("nan")
        wall = (time.monotonic() - wall0) if wall0 is not None else float("nan")
        sub.undeclare()
    print(json.dumps({
        "callback_ns": cb_lat, "loop_ns": loop_lat, "expected": n_expected, "last_seq": seqs[-1] if seqs else None,
        "overwritten": slot.overwritten, "cpu_s": cpu, "wall_s": wall,
    }), flush=True)


async def run_pub(settings: tp.ZenohSettings, rate: float, seconds: float, size: int) -> None:
    n = int(round(rate * seconds))
    period_ns = int(round(1e9 / rate))
    pad = b"\0" * (size - HEADER.size)
    async with tp.open_session(settings) as session:
        with tp.declare_publisher(session, KEY, tp.STATE) as pub:
            await tp.wait_for_subscribers(pub, 10.0)
            start = time.monotonic_ns() + 50_000_000
            for seq in range(n):
                deadline = start + seq * period_ns
                delay = (deadline - time.monotonic_ns()) / 1e9
                if delay > 0:
                    await asyncio.sleep(delay)
                pub.put(HEADER.pack(time.monotonic_ns(), seq, n) + pad)


# --------------------------------------------------------------------------- orchestration
def _spawn(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, __file__, *args], cwd=REPO, text=True,
        stdin=subprocess.PIPE, stdout=subprocess.PIPE,
    )


def _await_ready(p: subprocess.Popen[str]) -> None:
    assert p.stdout is not None
    line = p.stdout.readline().strip()
    if line != "ready":
        raise RuntimeError(f"child did not start (said {line!r})")


def one_case(topology: str, callback: str, rate: float, seconds: float, size: int) -> dict[str, object]:
    port = tp.free_tcp_port()
    ep = tp.loopback_endpoint(port)
    children: list[subprocess.Popen[str]] = []
    try:
        if topology == "star":
            router = _spawn("_router", ep)
            children.append(router)
            _await_ready(router)
            sub_args, pub_args = ["client", ep], ["client", ep]
        else:
            sub_args, pub_args = ["listen", ep], ["connect", ep]
        sub = _spawn("_sub", *sub_args, callback, str(seconds))
        children.append(sub)
        _await_ready(sub)
        pub = _spawn("_pub", *pub_args, str(rate), str(seconds), str(size))
        children.append(pub)
        out, _ = sub.communicate(timeout=seconds + 30)
        pub.wait(timeout=10)
    finally:
        for c in children:
            if c.poll() is None:
                if c.stdin is not None:
                    c.stdin.close()
                try:
                    c.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    c.kill()
                    c.wait()
    res = json.loads(out.strip().splitlines()[-1])
    row: dict[str, object] = {"topology": topology, "callback": callback, "received": len(res["callback_ns"]),
                              "expected": res["expected"], "overwritten": res["overwritten"],
                              "sub_cpu_pct": 100 * res["cpu_s"] / res["wall_s"] if res["wall_s"] else float("nan")}
    for name in ("callback", "loop"):
        us = np.asarray(res[f"{name}_ns"], dtype=float) / 1e3
        row[f"{name}_p50_us"] = float(np.percentile(us, 50))
        row[f"{name}_p99_us"] = float(np.percentile(us, 99))
        row[f"{name}_max_us"] = float(us.max())
    return row


def _settings(how: str, ep: str) -> tp.ZenohSettings:
    if how == "listen":
        return tp.ZenohSettings(mode="peer", listen=(ep,), scouting_delay=0.0)
    if how == "connect":
        return tp.ZenohSettings(mode="peer", connect=(ep,), connect_timeout=5.0)
    return tp.ZenohSettings(mode="client", connect=(ep,), connect_timeout=5.0)


def main(argv: list[str]) -> None:
    if argv and argv[0] == "_router":
        return run_router(argv[1])
    if argv and argv[0] == "_sub":
        return asyncio.run(run_sub(_settings(argv[1], argv[2]), argv[3], float(argv[4])))
    if argv and argv[0] == "_pub":
        return asyncio.run(run_pub(_settings(argv[1], argv[2]), float(argv[3]), float(argv[4]), int(argv[5])))
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rate", type=float, default=100.0, help="samples per second [Hz]")
    ap.add_argument("--seconds", type=float, default=10.0, help="duration of each case [s]")
    ap.add_argument("--size", type=int, default=200, help="payload size [bytes]")
    ap.add_argument("--topology", choices=["p2p", "star", "both"], default="both")
    ap.add_argument("--callback", choices=["indirect", "direct", "both"], default="both")
    a = ap.parse_args(argv)
    if a.size < HEADER.size:
        ap.error(f"--size must be at least {HEADER.size}")
    topologies = ["p2p", "star"] if a.topology == "both" else [a.topology]
    callbacks = ["indirect", "direct"] if a.callback == "both" else [a.callback]
    print(f"{a.rate:g} Hz, {a.size} B, {a.seconds:g} s per case; latencies in microseconds")
    print(f"{'topology':8} {'callback':8} {'recv':>9} {'cb p50':>7} {'cb p99':>7} {'cb max':>7} "
          f"{'loop p50':>8} {'loop p99':>8} {'loop max':>8} {'ovw':>4} {'sub cpu':>7}")
    for topology in topologies:
        for callback in callbacks:
            r = one_case(topology, callback, a.rate, a.seconds, a.size)
            print(f"{topology:8} {callback:8} {r['received']:>4}/{r['expected']:<4} "
                  f"{r['callback_p50_us']:7.0f} {r['callback_p99_us']:7.0f} {r['callback_max_us']:7.0f} "
                  f"{r['loop_p50_us']:8.0f} {r['loop_p99_us']:8.0f} {r['loop_max_us']:8.0f} {r['overwritten']:>4} "
                  f"{r['sub_cpu_pct']:6.1f}%", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
