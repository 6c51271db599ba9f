"""Start software Crazyflies: ``python -m plant.cfsim --count 4 --base-port 19850``.

Vehicle i listens on ``udp://HOST:(base-port + i)`` (cflib's UDP scan looks at 19850..19859) and
starts at ``--p0`` number i, or, without ``--p0``, on the floor at ``(i * spacing, 0, 0)``. Every
vehicle runs in this one process; for one process per vehicle, run the command once per vehicle
with ``--count 1``, a different ``--base-port`` and ``--instance`` each.

Once every port is bound, one line per vehicle (``cfsim <i> udp://HOST:PORT``) and then
``cfsim ready`` are printed on stdout. SIGINT or SIGTERM stops it (exit 0); a port that cannot be
bound ends it with exit code 1.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import math
import signal
import sys
from typing import Any

from plant.cfsim import realism, server
from plant.cfsim.estimator import EstimatorConfig
from plant.cfsim.firmware import FirmwareConfig
from plant.quadrotor import QuadrotorParams
from tether import evloop

log = logging.getLogger("tether.cfsim")


def _p0(text: str) -> tuple[float, float, float]:
    try:
        parts = tuple(float(c) for c in text.split(","))
    except ValueError:
        parts = ()
    if len(parts) != 3 or not all(math.isfinite(c) for c in parts):
        raise argparse.ArgumentTypeError(f"{text!r}: give a position as X,Y,Z in metres, e.g. 0,0.5,0")
    return parts


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m plant.cfsim", description=__doc__.split("\n")[0])
    ap.add_argument("--count", type=int, default=1, help="number of vehicles (default 1)")
    ap.add_argument("--base-port", type=int, default=19850, help="UDP port of vehicle 0 (default 19850)")
    ap.add_argument("--port", type=int, action="append", metavar="P",
                    help="UDP port of the next vehicle, instead of --base-port + i; give it once per vehicle")
    ap.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    ap.add_argument("--instance", type=int, default=0,
                    help="index of the first vehicle, reported in param cfsim.instance (default 0)")
    ap.add_argument("--p0", type=_p0, action="append", metavar="X,Y,Z",
                    help="start position [m] of the next vehicle; give it once per vehicle")
    ap.add_argument("--spacing", type=float, default=0.5,
                    help="without --p0: vehicle i starts at (i * spacing, 0, 0) [m] (default 0.5)")
    ap.add_argument("--trace", default=None, metavar="FILE",
                    help="record every vehicle's true state per 10 ms tick in FILE (k instance x y z vx vy vz "
                         "thrust supervisor)")
    real = ap.add_argument_group("realism (all off by default; seeded: a seed gives the same run)")
    real.add_argument("--seed", type=int, default=0,
                      help="seed of every random draw; vehicle i uses seed + instance (default 0)")
    real.add_argument("--noise", type=float, default=None, metavar="SIGMA_P",
                      help="estimator noise: position error std [m] per axis, e.g. 0.1 (Loco Positioning)")
    real.add_argument("--noise-vel", type=float, default=0.05, metavar="SIGMA_V",
                      help="with --noise: velocity error std [m/s] per axis (default 0.05)")
    real.add_argument("--noise-tau", type=float, default=0.5, metavar="S",
                      help="with --noise: correlation time of the errors [s] (default 0.5)")
    real.add_argument("--battery", action="store_true",
                      help="a battery that drains with thrust (pm.vbat, pm.state, pm.batteryLevel)")
    real.add_argument("--battery-mah", type=float, default=250.0, help="with --battery: capacity [mAh] (default 250)")
    real.add_argument("--battery-charge", type=float, default=1.0,
                      help="with --battery: state of charge at boot, 0..1 (default 1)")
    real.add_argument("--latency", type=float, default=0.0, metavar="MS",
                      help="link delay [ms] of every datagram, each way (default 0)")
    real.add_argument("--jitter", type=float, default=0.0, metavar="MS",
                      help="extra link delay, uniform in [0, MS] (default 0)")
    real.add_argument("--loss", type=float, default=0.0, metavar="P",
                      help="probability that a datagram is lost, each way, 0..1 (default 0)")
    radio = ap.add_argument_group("a Crazyradio-like link (off by default; --loss, --latency, --jitter then apply "
                                  "to it: --loss per attempt, --jitter never reorders)")
    radio.add_argument("--radio", action="store_true",
                       help="acknowledgements and bounded retries, in-order delivery, airtime shared per dongle")
    radio.add_argument("--radio-rate", type=float, default=1000.0, metavar="HZ",
                       help="with --radio: attempts per second one dongle carries, each way (default 1000)")
    radio.add_argument("--radio-retries", type=int, default=3, metavar="N",
                       help="with --radio: retransmissions before a packet is lost (default 3)")
    radio.add_argument("--per-radio", type=int, default=0, metavar="N",
                       help="with --radio: vehicles per simulated dongle (default 0: all of this process on one)")
    radio.add_argument("--degrade", action="append", default=[], metavar="T:P",
                       help="with --radio: from T seconds after start, attempts are lost with probability P "
                            "(repeat for more steps, in time order)")
    veh = ap.add_argument_group("the vehicle (every vehicle of this process)")
    veh.add_argument("--mass", type=float, action="append", metavar="KG",
                     help="vehicle mass [kg] (default: a Crazyflie 2.1's, 0.029); once for every vehicle, or once "
                          "per vehicle in order")
    veh.add_argument("--position-source", choices=["onboard", "extpos"], default="onboard",
                     help="onboard: a positioning deck measures the vehicle (default); extpos: only the "
                          "external positions a client sends (motion capture) reach the estimator")
    veh.add_argument("--vbat", type=float, default=None, metavar="V",
                     help="battery voltage [V] reported without --battery (default 3.9)")
    veh.add_argument("--radio-id", type=int, default=0xE7, metavar="N",
                     help="last byte of the radio address, matched by packed external positions (default 231)")
    ap.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    args = ap.parse_args(argv)
    if args.count < 1:
        ap.error(f"--count {args.count}: give at least 1")
    if args.port is not None and len(args.port) != args.count:
        ap.error(f"--port given {len(args.port)} times for --count {args.count}: give it once per vehicle or not at all")
    if args.port is not None and not all(1 <= p <= 65535 for p in args.port):
        ap.error(f"--port {args.port}: every port must lie in 1..65535")
    if args.port is None and not 1 <= args.base_port <= 65536 - args.count:
        ap.error(f"--base-port {args.base_port}: ports {args.base_port}..{args.base_port + args.count - 1} "
                 "must lie in 1..65535")
    if args.p0 is not None and len(args.p0) != args.count:
        ap.error(f"--p0 given {len(args.p0)} times for --count {args.count}: give it once per vehicle or not at all")
    if args.mass is not None and len(args.mass) not in (1, args.count):
        ap.error(f"--mass given {len(args.mass)} times for --count {args.count}: give it once for every vehicle, "
                 "once per vehicle, or not at all")
    for mass in args.mass or ():
        if not (math.isfinite(mass) and 0.005 <= mass <= 1.0):
            ap.error(f"--mass {mass}: give the vehicle's mass in kg, e.g. 0.032")
    if args.vbat is not None and not (math.isfinite(args.vbat) and 0.0 <= args.vbat <= 5.0):
        ap.error(f"--vbat {args.vbat}: give a 1-cell LiPo voltage in V, e.g. 3.9")
    if not 0 <= args.radio_id <= 255:
        ap.error(f"--radio-id {args.radio_id}: give the address's last byte, 0..255")
    if args.p0 is None and not math.isfinite(args.spacing):
        ap.error("--spacing must be a finite number of metres")
    try:
        args.noise_cfg = (realism.NoiseConfig(args.noise, args.noise_vel, args.noise_tau, args.seed)
                          if args.noise is not None else None)
        args.battery_cfg = (realism.BatteryConfig(capacity_mah=args.battery_mah, charge=args.battery_charge)
                            if args.battery else None)
        args.link_cfg = realism.LinkConfig(args.latency / 1000.0, args.jitter / 1000.0, args.loss, args.seed)
        args.radio_cfg = _radio(args) if args.radio else None
    except ValueError as e:
        ap.error(f"realism option: {e}")
    return args


def _radio(args: argparse.Namespace) -> realism.RadioConfig:
    """The ``--radio`` options as a :class:`realism.RadioConfig`; ``ValueError`` names the bad one."""
    steps = []
    for step in args.degrade:
        try:
            t, p = (float(x) for x in step.split(":"))
        except ValueError:
            raise ValueError(f"--degrade {step!r}: give T:P, seconds after start and a loss, e.g. 10:0.6") from None
        steps.append((t, p))
    if args.per_radio < 0:
        raise ValueError(f"--per-radio {args.per_radio}: give 0 (all on one dongle) or more")
    return realism.RadioConfig(rate=args.radio_rate, retries=args.radio_retries, loss=args.loss,
                               latency=args.latency / 1000.0, jitter=args.jitter / 1000.0,
                               degrade=tuple(steps), seed=args.seed)


def config(args: argparse.Namespace) -> server.SimConfig:
    vehicle: dict[str, Any] = {"estimator": EstimatorConfig(source=args.position_source), "radio_id": args.radio_id}
    if args.vbat is not None:
        vehicle["vbat"] = args.vbat
    starts = args.p0 or [(i * args.spacing, 0.0, 0.0) for i in range(args.count)]
    def noise(instance: int) -> realism.NoiseConfig | None:
        n = args.noise_cfg
        return None if n is None else realism.NoiseConfig(n.sigma_p, n.sigma_v, n.tau, n.seed + instance)

    return server.SimConfig(
        vehicles=tuple(
            server.VehicleConfig(port=args.port[i] if args.port else args.base_port + i, p0=p0,
                                 firmware=FirmwareConfig(instance=args.instance + i, noise=noise(args.instance + i),
                                                         battery=args.battery_cfg, **vehicle),
                                 quadrotor=None if not args.mass else QuadrotorParams(mass=args.mass[i % len(args.mass)]))
            for i, p0 in enumerate(starts)
        ),
        quadrotor=QuadrotorParams(),
        host=args.host,
        trace=args.trace,
        link=realism.LinkConfig() if args.radio_cfg else args.link_cfg,
        radio=args.radio_cfg,
        per_radio=args.per_radio,
    )


def _announce(uris: list[tuple[int, str]]) -> None:
    for i, uri in uris:
        print(f"cfsim {i} {uri}")
    print("cfsim ready", flush=True)


async def _main(cfg: server.SimConfig) -> None:
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    assert task is not None
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, task.cancel)
    with contextlib.suppress(asyncio.CancelledError):
        await server.run(cfg, on_ready=_announce)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s cfsim %(levelname)s %(message)s",
                        stream=sys.stderr)
    cfg = config(args)
    try:
        kind = evloop.choose()
    except evloop.LoopError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        evloop.run(_main(cfg), kind)
    except OSError as e:
        log.error("cannot serve %s:%d..%d: %s", cfg.host, cfg.vehicles[0].port, cfg.vehicles[-1].port, e)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
