"""How closely the software Crazyflie's body follows an uploaded trajectory: a figure-eight of
half-width 0.3 m (five 7th-order pieces, rest to rest) flown in several durations by the firmware
alone, ticked by hand in simulated time (no processes, no cflib; deterministic).

    python bench/cfsim_trajectory.py [--durations 6,8,10,12]

Prints, per duration, the largest distance per axis between the body and the polynomial, the
largest distance between the commanded setpoint and the polynomial (the evaluation itself; float32
coefficients) and the peak acceleration of the path.
"""

from __future__ import annotations

import argparse
import math
import struct

import numpy as np

from plant.cfsim import commander, crtp, firmware
from plant.quadrotor import Quadrotor, QuadrotorParams


def figure_eight(duration: float, pieces: int = 5, r: float = 0.3) -> list[tuple[float, np.ndarray]]:
    T = float(np.float32(duration / pieces))  # as the memory holds it
    out = []
    for k in range(pieces):
        t = np.linspace(0.0, T, 200)
        tau = (k * T + t) / duration
        phase = 2.0 * math.pi * (35 * tau**4 - 84 * tau**5 + 70 * tau**6 - 20 * tau**7)
        rows = [r * np.sin(phase), 0.5 * r * np.sin(2.0 * phase), 0.1 * np.sin(phase) ** 2, 0.3 * np.sin(phase)]
        out.append((T, np.array([np.polynomial.polynomial.polyfit(t, f, 7) for f in rows]).astype(np.float32)))
    return out


def point(pieces: list[tuple[float, np.ndarray]], t: float, der: int = 0) -> np.ndarray:
    for T, c in pieces:
        if t <= T:
            return np.array([np.polynomial.polynomial.polyval(t, np.polynomial.polynomial.polyder(row, der))
                             for row in c[:3]])
        t -= T
    T, c = pieces[-1]
    return np.array([np.polynomial.polynomial.polyval(T, row) for row in c[:3]]) if der == 0 else np.zeros(3)


def fly(duration: float) -> tuple[float, float, float]:
    pieces = figure_eight(duration)
    fw = firmware.Firmware(Quadrotor(QuadrotorParams(), np.zeros(3)))

    def send(port: crtp.Port, ch: int, data: bytes) -> None:
        fw.handle(crtp.Packet(port, ch, data))

    send(crtp.Port.SETPOINT_HL, 0, struct.pack("<BBff?f", 7, 0, 0.5, 0.0, False, 1.5))
    for _ in range(300):
        fw.tick()
    data = b"".join(struct.pack("<32ff", *c.ravel(), T) for T, c in pieces)
    for a in range(0, len(data), 24):
        send(crtp.Port.MEM, 2, struct.pack("<BI", 0, a) + data[a:a + 24])
    send(crtp.Port.SETPOINT_HL, 0, struct.pack("<BBBBIB", 6, 1, 1, 0, 0, len(pieces)))
    origin = np.array(fw.hl.pos)
    send(crtp.Port.SETPOINT_HL, 0, struct.pack("<BBBBBBf", 13, 0, 1, 0, 0, 1, 1.0))
    t0 = fw.t
    body = setpoint = 0.0
    for _ in range(int(duration * 100) + 100):
        t = fw.t - t0  # the setpoint of this tick is evaluated at t
        fw.tick()
        want = origin + point(pieces, t)
        sp = fw._applied
        assert isinstance(sp, commander.Track)
        setpoint = max(setpoint, float(np.abs(np.array(sp.pos) - want).max()))
        body = max(body, float(np.abs(fw.quad.p - (origin + point(pieces, fw.t - t0))).max()))
    acc = max(float(np.linalg.norm(point(pieces, t, 2))) for t in np.linspace(0.0, duration, 500))
    return body, setpoint, acc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--durations", default="6,8,10,12")
    args = ap.parse_args()
    print("| duration [s] | peak acceleration [m/s^2] | body off the path, max per axis [m] | setpoint off the polynomial [m] |")
    print("|---|---|---|---|")
    for d in (float(x) for x in args.durations.split(",")):
        body, sp, acc = fly(d)
        print(f"| {d:g} | {acc:.2f} | {body:.3f} | {sp:.1e} |")


if __name__ == "__main__":
    main()
