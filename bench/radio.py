"""The radio budget: how many packets a second fit on one simulated Crazyradio for 4 and 8 vehicles.

    python bench/radio.py [--counts 4,8] [--seconds 6] [--radio-rate 1000]

For each vehicle count and each rate set (setpoints up, position/velocity and acceleration log
blocks down, as the ``crazyflie`` plant streams them), starts ``python -m plant.cfsim --radio`` with
that many vehicles on one simulated dongle, connects real cflib to every vehicle from this process,
streams for ``--seconds`` (vehicles on the floor: the link is what is measured) while pinging ten
times a second as the plant does, and prints per rate set: what was asked per vehicle, the log
packets that came (share of those asked, the worst vehicle), the ping round trip (median and 95th
percentile over every vehicle's pings) and the dongle's counts (packets lost after every retry,
dropped for want of airtime, and the airtime used each way). A rate set fits when every vehicle
gets at least 99 % of its logs and nothing is dropped.
"""

from __future__ import annotations

import argparse
import contextlib
import re
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

RATE_SETS = [(100, 100, 100), (100, 100, 50), (50, 50, 25)]
"""(setpoints, position/velocity log, acceleration log) per vehicle [1/s]."""


def _free_ports(n: int) -> int:
    for base in range(20100, 40000, 16):
        ok = True
        for p in range(base, base + n):
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                try:
                    s.bind(("127.0.0.1", p))
                except OSError:
                    ok = False
                    break
        if ok:
            return base
    raise OSError("no free UDP ports")


def one(count: int, rates: tuple[int, int, int], seconds: float, radio_rate: float, cache: str) -> dict[str, float]:
    import cflib.crtp
    from cflib.crazyflie import Crazyflie
    from cflib.crazyflie.log import LogConfig
    from cflib.crtp.crtpstack import CRTPPort

    sp_rate, pv_rate, acc_rate = rates
    base = _free_ports(count)
    sim = subprocess.Popen([sys.executable, "-m", "plant.cfsim", "--radio", "--count", str(count), "--base-port",
                            str(base), "--radio-rate", str(radio_rate), "--log-level", "INFO"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           cwd=Path(__file__).resolve().parent.parent)
    assert sim.stdout is not None
    for line in sim.stdout:
        if line.strip() == "cfsim ready":
            break
    cflib.crtp.init_drivers()
    cfs: list[Crazyflie] = []
    counts = [0] * count
    rtts: list[float] = []
    lock = threading.Lock()
    stop = threading.Event()
    try:
        ready = []
        for i in range(count):
            cf = Crazyflie(rw_cache=cache)
            ev = threading.Event()
            cf.fully_connected.add_callback(lambda _u, ev=ev: ev.set())
            cf.open_link(f"udp://127.0.0.1:{base + i}")
            cfs.append(cf)
            ready.append(ev)
        for ev in ready:
            if not ev.wait(60):
                raise TimeoutError("a vehicle did not connect within 60 s")

        def on_echo(pk: object) -> None:
            data = bytes(pk.data)  # type: ignore[attr-defined]
            if len(data) == 9 and data[0] == 0x70:  # our pings: header, send time
                with lock:
                    rtts.append(time.monotonic() - struct.unpack("<d", data[1:])[0])

        for i, cf in enumerate(cfs):
            cf.link_statistics.stop()
            cf.add_port_callback(CRTPPort.LINKCTRL, on_echo)
            for name, rate, names in (("pv", pv_rate, ("x", "y", "z", "vx", "vy", "vz")), ("a", acc_rate, ("ax", "ay", "az"))):
                conf = LogConfig(name=name, period_in_ms=int(round(1000 / rate)))
                for n in names:
                    conf.add_variable(f"stateEstimate.{n}", "float")
                conf.data_received_cb.add_callback(lambda *_a, i=i: counts.__setitem__(i, counts[i] + 1))
                cf.log.add_config(conf)
                conf.start()

        def stream() -> None:
            from cflib.crtp.crtpstack import CRTPPacket

            k, t0 = 0, time.monotonic()
            while not stop.is_set():
                for cf in cfs:
                    cf.commander.send_setpoint(0.0, 0.0, 0.0, 0)
                if k % max(1, sp_rate // 10) == 0:
                    for cf in cfs:
                        pk = CRTPPacket()
                        pk.set_header(CRTPPort.LINKCTRL, 0)
                        pk.data = struct.pack("<Bd", 0x70, time.monotonic())
                        cf.send_packet(pk)
                k += 1
                time.sleep(max(0.0, t0 + k / sp_rate - time.monotonic()))

        time.sleep(1.0)  # the log blocks settle
        counts[:] = [0] * count
        with lock:
            rtts.clear()
        th = threading.Thread(target=stream, daemon=True)
        th.start()
        time.sleep(seconds)
        got = list(counts)
        stop.set()
        th.join()
    finally:
        for cf in cfs:
            with contextlib.suppress(Exception):
                cf.close_link()
        sim.send_signal(signal.SIGTERM)
        _, err = sim.communicate(timeout=20)
    m = re.search(r"radio 0: up (\d+) sent, (\d+) lost, (\d+) dropped \(queue\), (\d+) attempts; down (\d+) sent, "
                  r"(\d+) lost, (\d+) dropped \(queue\), (\d+) attempts", err)
    if m is None:
        raise RuntimeError(f"no radio counts from the simulator: {err[-500:]}")
    up_sent, up_lost, up_drop, up_att, dn_sent, dn_lost, dn_drop, dn_att = map(int, m.groups())
    asked = (pv_rate + acc_rate) * seconds
    r = np.array(rtts) * 1000.0
    return {"logs_min": min(got) / asked, "logs_mean": float(np.mean(got)) / asked,
            "rtt_p50": float(np.median(r)) if r.size else float("nan"),
            "rtt_p95": float(np.percentile(r, 95)) if r.size else float("nan"),
            "lost": up_lost + dn_lost, "dropped": up_drop + dn_drop, "sent": up_sent + dn_sent}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--counts", default="4,8")
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--radio-rate", type=float, default=1000.0)
    args = ap.parse_args()
    print(f"one simulated dongle, {args.radio_rate:g} attempts/s each way; {args.seconds:g} s per row; "
          "pings at 10 Hz per vehicle")
    print(f"{'vehicles':>8} {'setpoint Hz':>11} {'pv log Hz':>9} {'acc log Hz':>10} {'up pkt/s':>9} {'down pkt/s':>10} "
          f"{'logs (worst)':>12} {'ping p50 ms':>11} {'ping p95 ms':>11} {'lost':>5} {'dropped':>7}  fits")
    with tempfile.TemporaryDirectory() as cache:
        for n in (int(c) for c in args.counts.split(",")):
            for rates in RATE_SETS:
                r = one(n, rates, args.seconds, args.radio_rate, cache)
                up = n * (rates[0] + 10)
                down = n * (rates[1] + rates[2] + 10)
                fits = r["logs_min"] >= 0.99 and r["dropped"] == 0 and r["lost"] == 0
                print(f"{n:>8} {rates[0]:>11} {rates[1]:>9} {rates[2]:>10} {up:>9} {down:>10} "
                      f"{100 * r['logs_min']:>11.1f}% {r['rtt_p50']:>11.1f} {r['rtt_p95']:>11.1f} {r['lost']:>5} "
                      f"{r['dropped']:>7}  {'yes' if fits else 'no'}", flush=True)


if __name__ == "__main__":
    main()
