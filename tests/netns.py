"""A vehicle behind a radio link that can really be cut: a Linux network namespace joined to the host
by a veth pair, and an on-board Zenoh router inside it.

The model is a companion computer: the vehicle's agent and plant run in the namespace and talk to
each other through the on-board router on the namespace's own loopback (an on-board link that no
cut touches); the on-board router links to the swarm's router over the veth (the radio).
:meth:`Namespace.cut` takes the namespace's end of the veth down (the host's end loses its carrier,
so nothing leaks out by another route) and :meth:`Namespace.restore` brings it back.

Needs root and ``ip`` (iproute2); :func:`unavailable` says why not, for a skip. Every name is
unique to the creating process (``tether-pt-<pid>``, ``tpt<pid>h`` / ``tpt<pid>v``) and the /30
subnet is picked among ``10.231.0.0/16`` blocks no host interface uses, so concurrent runs do not
collide. :meth:`Namespace.destroy` deletes the veth pair and the namespace and kills what still runs
inside it (by pid: only this test's processes run there).

The on-board router is this module run as a program (``python -m tests.netns router ...``): a
zenoh-python session in router mode that listens on the namespace's loopback, connects to the
swarm's router, and retries that link quickly after a cut (Zenoh's default backoff grows to 4 s).
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import os
import shutil
import signal
import subprocess
import sys
from dataclasses import dataclass

SUBNETS = ipaddress.ip_network("10.231.0.0/16")


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10, check=check)


def unavailable() -> str | None:
    """Why a namespace cannot be made here (for ``pytest.skip``), or None."""
    if os.geteuid() != 0:
        return "needs root: creating a network namespace and a veth pair takes CAP_NET_ADMIN"
    if shutil.which("ip") is None:
        return "needs the `ip` command (iproute2) for network namespaces"
    probe = f"tether-probe-{os.getpid()}"
    made = _ip("netns", "add", probe, check=False)
    if made.returncode != 0:
        return f"`ip netns add` fails here: {made.stderr.strip()}"
    _ip("netns", "del", probe, check=False)
    return None


def _used_addresses() -> set[ipaddress.IPv4Address]:
    out = _ip("-o", "-4", "addr", "show").stdout
    used = set()
    for line in out.splitlines():
        parts = line.split()
        if "inet" in parts:
            used.add(ipaddress.ip_interface(parts[parts.index("inet") + 1]).ip)
    return used


def _free_subnet() -> ipaddress.IPv4Network:
    used = _used_addresses()
    blocks = list(SUBNETS.subnets(new_prefix=30))
    start = (os.getpid() * 7) % len(blocks)
    for n in range(len(blocks)):
        block = blocks[(start + n) % len(blocks)]
        if not any(a in block for a in used):
            return block
    raise RuntimeError(f"no free /30 in {SUBNETS}")


@dataclass
class Namespace:
    """One namespace and its veth pair; :meth:`create` makes them, :meth:`destroy` removes them."""

    name: str
    host_if: str
    ns_if: str
    host_addr: str = ""
    ns_addr: str = ""

    @classmethod
    def unique(cls, tag: str = "") -> Namespace:
        pid = os.getpid()
        return cls(name=f"tether-pt-{pid}{tag}", host_if=f"tpt{pid}{tag}h", ns_if=f"tpt{pid}{tag}v")

    def create(self) -> None:
        self.destroy()  # leftovers of an earlier process with the same pid
        block = _free_subnet()
        host, inside = list(block.hosts())
        self.host_addr, self.ns_addr = str(host), str(inside)
        steps = [
            ("netns", "add", self.name),
            ("link", "add", self.host_if, "type", "veth", "peer", "name", self.ns_if),
            ("link", "set", self.ns_if, "netns", self.name),
            ("addr", "add", f"{host}/30", "dev", self.host_if),
            ("link", "set", self.host_if, "up"),
            ("-n", self.name, "addr", "add", f"{inside}/30", "dev", self.ns_if),
            ("-n", self.name, "link", "set", self.ns_if, "up"),
            ("-n", self.name, "link", "set", "lo", "up"),
        ]
        for step in steps:
            done = _ip(*step, check=False)
            if done.returncode != 0:
                self.destroy()
                raise RuntimeError(f"ip {' '.join(step)}: {done.stderr.strip()}")

    def exec_prefix(self) -> list[str]:
        """The command prefix that runs a program inside the namespace (it execs, keeping the pid)."""
        return ["ip", "netns", "exec", self.name]

    def cut(self) -> None:
        """The radio goes down: the namespace's end of the veth is set down."""
        _ip("-n", self.name, "link", "set", self.ns_if, "down")

    def restore(self) -> None:
        _ip("-n", self.name, "link", "set", self.ns_if, "up")

    def link_up(self) -> bool:
        out = _ip("-n", self.name, "-br", "link", "show", self.ns_if, check=False).stdout
        return " UP " in f" {out} "

    def pids(self) -> list[int]:
        out = _ip("netns", "pids", self.name, check=False).stdout
        return [int(p) for p in out.split()]

    def destroy(self) -> None:
        """Kill what still runs inside, delete the veth pair (both ends) and the namespace. Idempotent."""
        if self.name in _ip("netns", "list", check=False).stdout.split():
            for pid in self.pids():
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        _ip("link", "del", self.host_if, check=False)
        _ip("netns", "del", self.name, check=False)


# =========================================================================== the on-board router
def router_command(listen: str, connect: str, lease: float, retry: float, parent_pid: int) -> list[str]:
    """Arguments (after a namespace prefix) that start the on-board router."""
    return [sys.executable, "-m", "tests.netns", "router", "--listen", listen, "--connect", connect,
            "--lease", repr(lease), "--retry", repr(retry), "--parent-pid", str(parent_pid)]


def _router(args: argparse.Namespace) -> int:
    import threading

    import zenoh

    from tether import transport as tp

    settings = tp.ZenohSettings(mode="router", listen=(args.listen,), connect=(args.connect,), lease=args.lease)
    config = tp.zenoh_config(settings)
    # Wait at most one period at open for the swarm's router, never give up on it, and retry every
    # `retry` seconds, at start and after the link is lost (Zenoh 1.10's router default backs off to
    # 4 s). Measured: with timeout_ms 0 a router tries once at open and never again, whatever
    # exit_on_failure says; with timeout_ms > 0 and exit_on_failure false it retries in the background.
    period = max(1, round(args.retry * 1000))
    config.insert_json5("connect/timeout_ms", str(period))
    config.insert_json5("connect/exit_on_failure", "false")
    config.insert_json5("connect/retry", json.dumps({"period_init_ms": period, "period_max_ms": period,
                                                     "period_increase_factor": 1.0}))
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    from tether import sched

    # the control processes' priority, as a deployment's router unit has (CPUSchedulingPolicy=rr): the
    # vehicle's agent and plant, at SCHED_RR by default, must not starve the router they talk through
    print(f"CPU scheduling: {sched.apply_best()[1]}", file=sys.stderr, flush=True)
    session = zenoh.open(config)
    try:
        print(f"router {session.zid()} listening on {args.listen}, linked to {args.connect}", file=sys.stderr,
              flush=True)
        while not stop.wait(0.5):
            if os.getppid() != args.parent_pid:
                break
    finally:
        session.close()
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.netns")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("router", help="an on-board Zenoh router (run it inside the namespace)")
    r.add_argument("--listen", required=True, help="on-board endpoint, e.g. tcp/127.0.0.1:7447")
    r.add_argument("--connect", required=True, help="the swarm's router, over the veth")
    r.add_argument("--lease", type=float, default=1.0)
    r.add_argument("--retry", type=float, default=0.25, help="seconds between attempts to (re)link [s]")
    r.add_argument("--parent-pid", type=int, required=True, help="stop when this process is gone")
    args = p.parse_args(argv)
    return _router(args)


if __name__ == "__main__":
    sys.exit(main())

