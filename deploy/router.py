"""A Zenoh router as a Python process: relays between the deployment's processes until SIGTERM.

No ``zenohd`` package is reachable here, so the router is a zenoh-python session opened in router
mode (``mode: "router"`` in its configuration); it routes and enforces the configuration's access
control like zenohd would, and declares nothing itself.

    python -m deploy.router --config /etc/tether/router.json5

``--priority P`` runs it at ``SCHED_RR`` P where the system permits it, else at the normal policy
with one line saying why (:func:`tether.sched.apply_best`); 0 is the normal policy. ``tether run``'s
operator gateway (``deploy/localtls.py``), which carries the operator's ``land`` and ``estop``,
takes :func:`tether.sched.gateway_priority` of the control processes' priority: one step below
them, so that an order preempts a busy host's normal work and a flood of the gateway's links never
delays a control loop. ``--idle`` runs it at the lowest CPU priority the kernel grants without
privileges (``SCHED_IDLE``, or else nice 19): a router of links that may wait for an idle CPU (an
order through it may wait as long).

Prints one line ``router <zid> listening on <endpoints>`` on stderr once it listens (and, with
``connect`` endpoints and ``exit_on_failure``, once it is linked to them). Exit status:
0 stopped by SIGTERM/SIGINT, 1 Zenoh could not open (address in use, bad certificate, ...), 2 bad
configuration (not a router configuration, unreadable file).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading

from tether import transport as tp
from tether import sched

log = logging.getLogger("tether")

STOP_SIGNALS = {signal.SIGTERM, signal.SIGINT}


def check_router_config(path: str) -> list[str]:
    """The listen endpoints of the router configuration at ``path``. Raises
    :class:`~tether.transport.SettingsError` if the file is not a router configuration that listens."""
    config = tp.zenoh_config(tp.ZenohSettings(config_file=path))
    mode = json.loads(config.get_json("mode"))
    if mode != "router":
        raise tp.SettingsError([("mode", f"is {mode!r} in {path}; a router's configuration has mode \"router\" "
                                         "(use the router.json5 written by tether deploy-gen)")])
    endpoints = json.loads(config.get_json("listen/endpoints"))
    if isinstance(endpoints, dict):
        endpoints = endpoints.get("router", [])
    if not endpoints:
        raise tp.SettingsError([("listen.endpoints", f"is empty in {path}; a router must listen, "
                                                     "e.g. [\"tls/0.0.0.0:7447\"]")])
    return list(endpoints)


def serve(path: str, watch_pid: int | None = None) -> int:
    """Run the router of configuration ``path`` until SIGTERM or SIGINT (or, with ``watch_pid``, until
    its parent, of that id, is gone); returns the exit status.

    Blocks. Python's handlers for the stop signals only set an event, which the main thread checks
    at least once a second, so the session is always closed whichever thread the signal hit."""
    try:
        endpoints = check_router_config(path)
    except tp.SettingsError as exc:
        log.error("%s", exc)
        return 2
    stop = threading.Event()
    got: list[int] = []

    def on_signal(signum: int, _frame: object) -> None:
        got.append(signum)
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in STOP_SIGNALS}
    try:
        with tp.open_session(tp.ZenohSettings(config_file=path)) as session:
            log.info("router %s listening on %s", session.info.zid(), ", ".join(endpoints))
            while not stop.wait(0.5 if watch_pid else 1.0):
                if watch_pid and os.getppid() != watch_pid:
                    log.warning("process %d, which started this router, is gone: stopping", watch_pid)
                    break
            else:
                log.info("stopping on %s", signal.Signals(got[0]).name)
    except tp.TransportError as exc:
        log.error("%s", exc)
        return 1
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0


def _priority(text: str) -> int:
    try:
        x = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer; give 1..99 (SCHED_RR) or 0") from None
    if (why := sched.check_priority(x)) is not None:
        raise argparse.ArgumentTypeError(why)
    return x


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m deploy.router", description=__doc__.splitlines()[0])
    p.add_argument("--config", required=True, help="the router's Zenoh JSON5 file (router.json5 from tether deploy-gen)")
    level = p.add_mutually_exclusive_group()
    level.add_argument("--priority", type=_priority, default=None, metavar="P",
                       help="run at SCHED_RR P (1..99) where permitted, else at the normal policy (said in one "
                            "line); 0: the normal policy")
    level.add_argument("--idle", action="store_true",
                       help="run at the lowest CPU priority (SCHED_IDLE, else nice 19): a router of links that "
                            "may wait for an idle CPU")
    p.add_argument("--watch-pid", type=int, default=None,
                   help="stop when the process of this id, which started this router, is gone")
    p.add_argument("--log-level", default="INFO")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=getattr(logging, args.log_level.upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s router: %(message)s")
    if args.idle:
        log.info("CPU priority: %s", sched.lower_priority())
    elif args.priority is not None:  # before the session opens: Zenoh's threads inherit it
        applied, line = sched.apply_best(args.priority)
        (log.info if applied == args.priority else log.warning)("CPU priority: %s", line)
    return serve(args.config, args.watch_pid)


if __name__ == "__main__":
    sys.exit(main())
