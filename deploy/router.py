"""A Zenoh router as a Python process: relays between the deployment's processes until SIGTERM.

No ``zenohd`` package is reachable here, so the router is a zenoh-python session opened in router
mode (``mode: "router"`` in its configuration); it routes and enforces the configuration's access
control like zenohd would, and declares nothing itself.

    python -m deploy.router --config /etc/tether/router.json5

Prints one line ``router <zid> listening on <endpoints>`` on stderr once it listens. Exit status:
0 stopped by SIGTERM/SIGINT, 1 Zenoh could not open (address in use, bad certificate, ...), 2 bad
configuration (not a router configuration, unreadable file).
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading

from tether import transport as tp

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


def serve(path: str) -> int:
    """Run the router of configuration ``path`` until SIGTERM or SIGINT; returns the exit status.

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
            while not stop.wait(1.0):
                pass
            log.info("stopping on %s", signal.Signals(got[0]).name)
    except tp.TransportError as exc:
        log.error("%s", exc)
        return 1
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m deploy.router", description=__doc__.splitlines()[0])
    p.add_argument("--config", required=True, help="the router's Zenoh JSON5 file (router.json5 from tether deploy-gen)")
    p.add_argument("--log-level", default="INFO")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=getattr(logging, args.log_level.upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s router: %(message)s")
    return serve(args.config)


if __name__ == "__main__":
    sys.exit(main())
