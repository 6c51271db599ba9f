"""The operator's start command on a deployment: wait for every process, then announce tick 0.

On one machine ``tether run`` is the launcher; on companion computers each process is started by
its own service and waits, after declaring its liveliness token, for the start message on
``tether/<ns>/control/0/start``. This command (run on the ground station with the ``control-0``
identity) waits until the leader, every agent, every plant and the recorder hold their tokens, then
publishes ``Start(epoch = now + lead)``: every process ticks at ``epoch + k h`` on its own clock,
so the hosts' clocks must agree (NTP/chrony; a node refuses a start more than an hour off).

    python -m deploy.start --mission /etc/tether/mission.toml --zenoh-config /etc/tether/control-0.json5

Exit status: 0 started, 1 a process did not come up in time (named), 2 bad input.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import time
from pathlib import Path

from tether import catalog, evloop
from tether import mission as ms
from tether import transport as tp
from tether import wire

log = logging.getLogger("tether")


def members(m: ms.Mission) -> list[tuple[str, int]]:
    """Every process whose token the start waits for: leader, agents, plants, recorder."""
    return [("leader", m.leader.id), *[(r, a) for a in m.agent_ids for r in ("agent", "plant")], ("recorder", 0)]


async def start(m: ms.Mission, settings: tp.ZenohSettings, ns: str | None = None, lead: float = 3.0,
                timeout: float = 120.0) -> float:
    """Wait (up to ``timeout`` [s]) for every member's token, publish the start instant
    ``now + lead`` [s since the Unix epoch] (longer where a Crazyflie must take off in it:
    :func:`tether.mission.start_lead`), and return it at that instant. Raises :class:`~tether.transport.TokensMissing`
    naming the absent processes."""
    keys = wire.Keys(ns or m.name)
    lead = ms.start_lead(m, lead)
    async with tp.open_session(settings) as session:
        tokens = [keys.token(r, i) for r, i in members(m)]
        await tp.wait_for_tokens(session, tokens, timeout)
        log.info("all %d processes are up", len(tokens))
        pub = tp.declare_publisher(session, keys.start, tp.SYNC)
        try:
            await tp.wait_for_subscribers(pub, timeout)
            epoch = time.time() + lead
            pub.put(wire.encode(wire.Start(sender=0, seq=0, k=0, t=0.0, epoch=epoch)))
            # hold the link until tick 0, so that closing the session cannot cut the announcement
            # short on its way through the router
            await asyncio.sleep(max(0.0, epoch - time.time()))
        finally:
            pub.undeclare()
    log.info("tick 0 at %.3f (in %.1f s); the run lasts %g s", epoch, lead, m.duration)
    return epoch


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m deploy.start", description=__doc__.splitlines()[0])
    p.add_argument("--mission", required=True, help="mission file (the copy on this host) or shipped name")
    p.add_argument("--zenoh-config", required=True, help="this host's control-0.json5 (from tether deploy-gen)")
    p.add_argument("--ns", default=None, help="key namespace (default: the mission name)")
    p.add_argument("--lead", type=float, default=3.0, help="seconds from the announcement to tick 0")
    p.add_argument("--timeout", type=float, default=120.0, help="how long to wait for every process [s]")
    p.add_argument("--log-level", default="INFO")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=getattr(logging, args.log_level.upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s start: %(message)s")
    if not args.lead > 0 or not args.timeout > 0:
        print("error: --lead and --timeout are seconds > 0", file=sys.stderr)
        return 2
    try:
        m = ms.load(catalog.resolve(args.mission))
        settings = tp.ZenohSettings(config_file=str(Path(args.zenoh_config)))
        tp.zenoh_config(settings)
        evloop.choose()
    except (ms.MissionError, tp.SettingsError, evloop.LoopError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        evloop.run(start(m, settings, args.ns, args.lead, args.timeout))
    except tp.TokensMissing as exc:
        log.error("%s", exc)
        return 1
    except (tp.TransportError, TimeoutError) as exc:
        log.error("%s", exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
