"""``tether rehearse DEPLOY_DIR --out RUN``: a generated deployment flown on one machine, host by host.

What ``tether deploy-gen`` wrote for companion computers is run here as written, each host in a
network namespace of its own (root only, like ``ip netns``):

* **Hosts.** Every host directory ``DEPLOY_DIR/hosts/<host>/`` is placed at its address, read from
  its certificates' subject alternative names (what the hosts file gave, and what the others dial
  and verify; a DNS name: see Names). Host directories with one address are one machine (router, leader and recorder on
  a ground station): one namespace. Each namespace holds one veth whose other end is a port of a
  Linux bridge, and the bridge lives in a namespace of its own (the "switch"): nothing is added to
  this machine's own network, no address, route or interface. Each host address is a /32 with an
  on-link default route, so addresses of any subnets reach each other over the bridge.
* **Processes.** Every service unit ``hosts/<host>/systemd/*.service`` is parsed (``ExecStart``,
  ``Type``, ``Restart``, ``RestartSec``, ``WorkingDirectory``); its command line runs unchanged in its
  host's namespace, with the configuration files it names, except for what systemd itself would
  substitute (``%%``, ``%n``, ``%N``, ``%p``, ``%i``, ``%H``) and one thing a test machine lacks: a
  program path that does not exist here (the hosts file's ``tether`` or ``python``, e.g.
  ``/opt/tether/venv/bin/tether``) runs as this interpreter (``python -m cli`` for ``tether``).
  ``CPUSchedulingPolicy=`` and ``CPUSchedulingPriority=`` are applied as systemd applies them, with
  ``chrt`` (the control units run at ``SCHED_RR``). ``User=`` is not applied (the processes run as
  root, in their namespace). ``--duration S`` adds
  ``--duration S`` to every tether process (the mission file stays as generated); ``--skew HOST=S``
  adds ``--clock-skew S`` to every tether process of a host (an unsynchronised host).
* **Order, as an operator would.** The router's unit first (``tether-router``; until it logs that
  it listens), then every other long-running unit, then the one-shot ``tether-start`` on the leader's
  host, which waits for every process's liveliness token and announces tick 0.
* **Crazyflies.** A radio unit (``tether-radio-<k>``: every Crazyflie of one dongle, ``python -m
  cli.radio``) gets ``--duration`` and ``--clock-skew`` for each of its vehicles. With ``--sitl``
  the software Crazyflies of the mission's ``udp://`` plants (:mod:`deploy.sitl`) are started in the
  radio host's namespace, at the radio unit's scheduling, before the units, and stopped after them:
  the lab's deployment, flown against simulated vehicles.
* **Partitions.** ``--partition A:B@T+D`` cuts the machines of host directories A and B apart from
  mission time T for D seconds (two sites' routers): a blackhole route to the other's address in
  each namespace (iproute2 only: no netfilter, no kernel netem), removed at T + D.
* **Restarts.** ``Restart=on-failure`` restarts a unit that exits with a failure status or a signal
  after ``RestartSec``; ``Restart=always`` (the router) restarts it on any exit. A unit can be killed
  (SIGKILL) at a mission time with ``--kill UNIT@T`` to rehearse what its ``Restart=`` does.
* **The end.** The run ends when every unit but the router has exited and is not due a restart
  (every process exits 0 after the last tick), or :data:`END_GRACE` after the mission's end (a unit
  restarted after the run waits for a start that will not come), or after ``--timeout``. Then everything is torn down:
  every process (SIGTERM, SIGKILL after a grace), whatever still runs in a namespace (by pid), every
  namespace (which removes its veth and, with the switch, the bridge). The same happens on Ctrl-C
  or SIGTERM. ``RUN/rehearsal.json`` lists the namespaces, addresses, commands, exits and restarts;
  ``RUN/logs/<unit>.log`` each unit's output; the recorder's ``run.npz`` (and ``run.mcap``) is copied
  from its unit's ``--out`` into ``RUN`` (a ``run.npz`` and ``run.mcap`` left there by an earlier run
  are removed first): the same run file as ``tether run`` writes. A second Ctrl-C during the teardown is ignored.
* **Files.** As ``tether run`` makes its own (``tether/safefs.py``): ``RUN`` (and the recorder unit's
  ``--out``) must be the user's and writable by nobody else, on a path others cannot redirect, or the
  rehearsal exits 2 before anything starts; every log is made (appended to, across a unit's restarts)
  following no link, a log that is a link or another user's file refused (exit 2); the run files and
  ``rehearsal.json`` are written under an exclusive temporary name and renamed into place.

* **Names.** A host the hosts file names by DNS name (``uav1.local``) is put at an address of
  :data:`NAME_NET`, and every namespace resolves every such name to its host's address (a hosts
  file per namespace, :data:`NETNS_ETC`): the deployment a lab flies is the one it rehearses.
* **The truth.** At the end the safety events every agent and plant logged on its own host that
  the run file lacks (a site cut off from the recorder by a partition) are merged into ``run.npz``
  (:mod:`deploy.sitelogs`), and ``RUN/events.json`` lists the units that died and the run's
  failsafes and divergences. An ``--out`` that holds an earlier run (``rehearsal.json``, a run
  file, a unit log with something in it) is refused unless ``--replace`` is given, which removes
  those files first: a rehearsal never reads or appends to an earlier run's logs.

Exit status, as ``tether run``'s (``docs/exit-status.md``, :mod:`deploy.outcome`): 0 the run ended
and was recorded, clean; 3 a failsafe fired or a value diverged; 4 a process died (a unit exited
with a failure status or a signal while the run went on, restarted or not); 5 recorded with samples
missing; 1 the start failed, the run did not end in time, or nothing was recorded; 2 bad input (not
root, not a deployment, an address a namespace cannot take, an unsafe ``--out`` or one holding an
earlier run), before anything starts; 130 interrupted.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import logging
import os
import re
import secrets
import shlex
import shutil
import signal
import stat
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from deploy import inject, outcome
from tether import mission as ms
from tether import safefs, sched

log = logging.getLogger("tether")

REPO = Path(__file__).resolve().parents[1]
PREFIX = "tether-rh"
"""Every namespace a rehearsal makes is named ``tether-rh<pid>-<...>`` (the creating process's pid)."""
END_GRACE = 30.0
"""Units still running this long after the mission's end [s] are stopped (and the rehearsal fails)."""
ROUTER_UP = 30.0
"""How long to wait for the router's "listening" line [s]."""


class RehearseError(ValueError):
    """The rehearsal cannot start as asked; the message says why and what to do."""


# --------------------------------------------------------------------------- units
@dataclass
class Unit:
    """One generated service unit, as systemd would read the parts a rehearsal uses."""

    name: str
    """``tether-agent-2`` (the file name without ``.service``)."""
    host: str
    argv: list[str]
    """``ExecStart`` split as systemd splits it, specifiers substituted."""
    kind: str = "simple"
    """``Type=``: ``simple`` or ``oneshot``."""
    restart: str = "no"
    restart_sec: float = 0.1
    workdir: str | None = None
    scheduling: tuple[str, int] | None = None
    """``CPUSchedulingPolicy=`` (``rr``, ``fifo``, ``other``, ``batch``, ``idle``) and
    ``CPUSchedulingPriority=``, if the unit sets a policy."""

    @property
    def role(self) -> str:
        return self.name.removeprefix("tether-").split("-", 1)[0]


_SPECIFIER = re.compile(r"%(.)")


def parse_unit(path: Path, host: str) -> Unit:
    """The rehearsal's view of a unit file: the ``[Service]`` keys it uses. Raises
    :class:`RehearseError` naming the file for a unit without ``ExecStart``."""
    name = path.name.removesuffix(".service")
    values: dict[str, str] = {}
    section = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
            continue
        key, sep, value = line.partition("=")
        if sep and section == "Service":
            values[key.strip()] = value.strip()
    if "ExecStart" not in values:
        raise RehearseError(f"{path}: no ExecStart= in [Service]; is this a unit written by tether deploy-gen?")
    prefix, stem = name.split("@", 1) if "@" in name else (name, "")
    spec = {"%": "%", "n": path.name, "N": name, "p": prefix, "i": stem, "I": stem, "H": host}

    def sub(mt: re.Match[str]) -> str:
        if mt.group(1) not in spec:
            raise RehearseError(f"{path}: specifier %{mt.group(1)} in ExecStart is not one a rehearsal fills "
                                f"({', '.join('%' + k for k in spec)})")
        return spec[mt.group(1)]

    line = values["ExecStart"].lstrip("-@:+!")  # systemd's prefixes (ignore failure, argv0, privileges)
    argv = [_SPECIFIER.sub(sub, a) for a in shlex.split(line)]
    sec = values.get("RestartSec", "0.1").removesuffix("s")
    try:
        restart_sec = float(sec)
    except ValueError:
        raise RehearseError(f"{path}: RestartSec={values['RestartSec']} is not a number of seconds") from None
    return Unit(name, host, argv, values.get("Type", "simple"), values.get("Restart", "no"), restart_sec,
                values.get("WorkingDirectory"), _scheduling(path, values))


SCHED_POLICIES = ("other", "batch", "idle", "fifo", "rr")
"""systemd's ``CPUSchedulingPolicy=`` values (``chrt``'s options of the same names)."""


def _scheduling(path: Path, values: dict[str, str]) -> tuple[str, int] | None:
    """A unit's ``CPUSchedulingPolicy=`` and ``CPUSchedulingPriority=`` (None without a policy)."""
    policy = values.get("CPUSchedulingPolicy")
    if policy is None:
        if "CPUSchedulingPriority" in values:
            raise RehearseError(f"{path}: CPUSchedulingPriority= without CPUSchedulingPolicy=; give both")
        return None
    if policy not in SCHED_POLICIES:
        raise RehearseError(f"{path}: CPUSchedulingPolicy={policy} is not one of {', '.join(SCHED_POLICIES)}")
    text = values.get("CPUSchedulingPriority", "0")
    try:
        priority = int(text)
    except ValueError:
        raise RehearseError(f"{path}: CPUSchedulingPriority={text} is not an integer") from None
    realtime = policy in ("fifo", "rr")
    if not (sched.RR_MIN <= priority <= sched.RR_MAX if realtime else priority == 0):
        raise RehearseError(f"{path}: CPUSchedulingPriority={priority} with CPUSchedulingPolicy={policy}: give "
                            + (f"{sched.RR_MIN}..{sched.RR_MAX}" if realtime else "0 (or none)"))
    return policy, priority


def host_address(hdir: Path) -> str:
    """The host's address: the first subject alternative name of a certificate of one of its processes."""
    for crt in sorted((hdir / "tls").glob("*.crt")):
        if crt.name == "ca.crt":
            continue
        out = subprocess.run(["openssl", "x509", "-in", str(crt), "-noout", "-ext", "subjectAltName"],
                             capture_output=True, text=True, timeout=10)
        names = re.findall(r"(?:IP Address|DNS):([^\s,]+)", out.stdout)
        if names:
            return names[0]
    raise RehearseError(f"{hdir}: no certificate with an address (tls/<process>.crt); is this a host directory "
                        "written by tether deploy-gen?")


@dataclass
class Plan:
    """What a rehearsal of one deployment runs."""

    deploy: Path
    hosts: dict[str, str]
    """Host directory name -> IPv4 address (a DNS name's is the one :data:`NAME_NET` gave it)."""
    units: list[Unit]
    names: dict[str, str] = field(default_factory=dict)
    """DNS name the hosts file gave -> the address the rehearsal puts that host at (every namespace
    resolves the name to it: :data:`NETNS_ETC`)."""

    @property
    def machines(self) -> dict[str, list[str]]:
        """Address -> the host directories on it (one namespace each address)."""
        out: dict[str, list[str]] = {}
        for host, addr in self.hosts.items():
            out.setdefault(addr, []).append(host)
        return out


NAME_NET = ipaddress.ip_network("10.78.0.0/16")
"""Where a rehearsal puts hosts that the hosts file names by DNS name (one address per distinct
name, skipping the addresses other hosts were given)."""
NETNS_ETC = Path("/etc/netns")
"""``ip netns exec NS`` bind-mounts ``/etc/netns/NS/hosts`` over ``/etc/hosts`` for the command it
runs (iproute2's per-namespace configuration): a rehearsal writes there each name's address, for
its namespaces only, and removes it at the teardown."""


def _is_ip(addr: str) -> bool:
    try:
        ipaddress.ip_address(addr)
    except ValueError:
        return False
    return True


def plan(deploy: Path) -> Plan:
    """Read a generated deployment. Raises :class:`RehearseError` naming what is wrong and the fix.
    A host named by a DNS name in the hosts file is put at an address of :data:`NAME_NET`, and every
    namespace resolves the name to it (:attr:`Plan.names`)."""
    root = deploy / "hosts"
    if not root.is_dir():
        raise RehearseError(f"{deploy}: no hosts/ directory; give the --out of tether deploy-gen")
    hosts: dict[str, str] = {}
    units: list[Unit] = []
    given = {hdir.name: host_address(hdir) for hdir in sorted(p for p in root.iterdir() if p.is_dir())}
    taken = {a for a in given.values() if _is_ip(a)}
    free = (str(ip) for ip in NAME_NET.hosts() if str(ip) not in taken)
    names = {name: next(free) for name in sorted({a for a in given.values() if not _is_ip(a)})}
    for hdir in sorted(p for p in root.iterdir() if p.is_dir()):
        addr = names.get(given[hdir.name], given[hdir.name])
        ip = ipaddress.ip_address(addr)
        if ip.version != 4 or ip.is_loopback or ip.is_unspecified or ip.is_multicast:
            raise RehearseError(f"host {hdir.name}: address {addr} cannot be a host of its own in a namespace (every "
                                "namespace has its own loopback); give each host a unicast IPv4 address in the hosts "
                                "file, e.g. 10.77.0.11, and generate again")
        hosts[hdir.name] = addr
        for path in sorted((hdir / "systemd").glob("*.service")):
            units.append(parse_unit(path, hdir.name))
    if not hosts or not units:
        raise RehearseError(f"{deploy}: no host directories with service units under hosts/")
    roles = {u.role for u in units}
    for need, role in (("tether-router", "router"), ("tether-start", "start")):
        if role not in roles:
            raise RehearseError(f"{deploy}: no {need}.service among the units; generate the deployment again")
    scheduled = [u.name for u in units if u.scheduling is not None]
    if scheduled and shutil.which("chrt") is None:
        raise RehearseError(f"unit {scheduled[0]} sets CPUSchedulingPolicy=, which a rehearsal applies with chrt "
                            "(util-linux): install it")
    return Plan(deploy, hosts, units, names)


TETHER_ROLES = ("agent", "plant", "leader", "recorder", "world", "radio")
"""Units whose program is a tether process (they take ``--duration`` and ``--clock-skew``; a radio
host's, each of its vehicles)."""
PLANT_ROLES = ("plant", "world", "radio")
"""Units whose logs hold plants' watchdog events."""


def command(u: Unit, duration: float | None, skew: float = 0.0) -> list[str]:
    """The command a unit runs here: its ExecStart, with a program path this machine lacks replaced
    by this interpreter, and ``--duration`` (and a host's ``--clock-skew``) added to tether
    processes when asked."""
    argv = list(u.argv)
    prog = argv[0]
    if not (os.path.isfile(prog) and os.access(prog, os.X_OK)):
        base = os.path.basename(prog)
        if base == "tether":
            argv = [sys.executable, "-m", "cli", *argv[1:]]
        elif base.startswith("python"):
            argv = [sys.executable, *argv[1:]]
        else:
            raise RehearseError(f"unit {u.name}: its program {prog} does not exist here and is neither tether nor "
                                "python; install it at that path")
    extra = []
    if duration is not None and u.role in TETHER_ROLES:
        extra += ["--duration", repr(duration)]
    if skew and u.role in TETHER_ROLES:
        extra += ["--clock-skew", repr(skew)]
    if u.role != "radio" or "--" not in argv:
        return argv + extra
    first = argv.index("--")  # python -m cli.radio -- PLANT_ARGS -- PLANT_ARGS ...: each vehicle's options
    out = argv[:first]
    for k, a in enumerate(argv[first:], first):
        if a == "--" and k > first:
            out += extra
        out.append(a)
    return out + extra


def recorder_out(units: list[Unit]) -> Path | None:
    for u in units:
        if u.role == "recorder" and "--out" in u.argv:
            return Path(u.argv[u.argv.index("--out") + 1])
    return None


# --------------------------------------------------------------------------- namespaces
def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=15)
    if check and done.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {done.stderr.strip()}")
    return done


def unavailable() -> str | None:
    """Why namespaces cannot be made here, or None."""
    if os.geteuid() != 0:
        return "needs root: a rehearsal makes network namespaces, veth pairs and a bridge (CAP_NET_ADMIN); run it with sudo"
    if shutil.which("ip") is None:
        return "needs the `ip` command (iproute2)"
    if shutil.which("openssl") is None:
        return "needs `openssl` to read the hosts' addresses from their certificates"
    return None


def namespaces_of(pid: int) -> list[str]:
    """The namespaces a rehearsal of process ``pid`` made that still exist."""
    out = _ip("netns", "list", check=False).stdout
    return [ln.split()[0] for ln in out.splitlines() if ln.split() and ln.split()[0].startswith(f"{PREFIX}{pid}-")]


@dataclass
class Network:
    """The switch namespace with its bridge, and one namespace per machine."""

    tag: str = field(default_factory=lambda: f"{PREFIX}{os.getpid()}")
    spaces: dict[str, str] = field(default_factory=dict)
    """Address -> namespace name."""

    @property
    def switch(self) -> str:
        return f"{self.tag}-sw"

    def create(self, machines: dict[str, list[str]], names: dict[str, str] | None = None) -> None:
        """Make the switch and one namespace per machine (address -> its host directories); with
        ``names`` (DNS name -> address), each namespace resolves those names (:data:`NETNS_ETC`)."""
        self.destroy()
        _ip("netns", "add", self.switch)
        self.spaces["switch"] = self.switch
        _ip("-n", self.switch, "link", "set", "lo", "up")
        _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", self.switch, "link", "set", "br0", "up")
        for n, (addr, hosts) in enumerate(machines.items()):
            ns = f"{self.tag}-{n}-{hosts[0]}"[:60]
            _ip("netns", "add", ns)
            self.spaces[addr] = ns
            _ip("-n", self.switch, "link", "add", f"v{n}", "type", "veth", "peer", "name", "eth0", "netns", ns)
            _ip("-n", self.switch, "link", "set", f"v{n}", "master", "br0")
            _ip("-n", self.switch, "link", "set", f"v{n}", "up")
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", ns, "addr", "add", f"{addr}/32", "dev", "eth0")
            _ip("-n", ns, "link", "set", "eth0", "up")
            _ip("-n", ns, "route", "add", "default", "dev", "eth0")
            if names:
                etc = NETNS_ETC / ns
                etc.mkdir(parents=True, exist_ok=True)
                lines = ["127.0.0.1 localhost", "::1 localhost", *(f"{a} {n}" for n, a in sorted(names.items()))]
                (etc / "hosts").write_text("\n".join(lines) + "\n")

    def cut(self, a: str, b: str) -> None:
        """No packet between machines ``a`` and ``b`` (addresses) any more: each drops what it would
        send the other (a blackhole route: iproute2 alone, no netfilter or netem needed), so their
        links time out on their leases as over a lost radio link."""
        _ip("-n", self.spaces[a], "route", "add", "blackhole", f"{b}/32")
        _ip("-n", self.spaces[b], "route", "add", "blackhole", f"{a}/32")

    def heal(self, a: str, b: str) -> None:
        _ip("-n", self.spaces[a], "route", "del", "blackhole", f"{b}/32", check=False)
        _ip("-n", self.spaces[b], "route", "del", "blackhole", f"{a}/32", check=False)

    def destroy(self) -> None:
        """Kill whatever still runs inside (by pid), delete every namespace (their veths and the
        bridge go with them). Idempotent."""
        names = set(self.spaces.values()) | set(n for n in namespaces_of(os.getpid()) if n.startswith(self.tag + "-"))
        for ns in names:
            for p in _ip("netns", "pids", ns, check=False).stdout.split():
                try:
                    os.kill(int(p), signal.SIGKILL)
                except ProcessLookupError:
                    pass
        for ns in names:
            _ip("netns", "del", ns, check=False)
            shutil.rmtree(NETNS_ETC / ns, ignore_errors=True)
        self.spaces.clear()


# --------------------------------------------------------------------------- processes
@dataclass
class Running:
    unit: Unit
    argv: list[str]
    log_path: Path
    proc: subprocess.Popen[bytes] | None = None
    starts: list[float] = field(default_factory=list)
    """Wall times [s since the Unix epoch] the unit was (re)started."""
    pids: list[int] = field(default_factory=list)
    """The process id of each start."""
    exits: list[tuple[float, int]] = field(default_factory=list)
    """(wall time, status) of each exit."""
    due: float | None = None
    """Monotonic time a restart is due, if one is."""
    done: bool = False
    """Exited and not due a restart."""

    def spawn(self, ns: str, env: dict[str, str]) -> None:
        """Start the unit's command in namespace ``ns``, its output appended to its log (which
        :func:`rehearse` made, under ``--out``'s real path; opened following no link)."""
        cwd = self.unit.workdir if self.unit.workdir and os.path.isdir(self.unit.workdir) else None
        with safefs.Dir.open(self.log_path.parent) as logs, logs.open_append(self.log_path.name) as fh:
            policy = self.unit.scheduling
            chrt = [] if policy is None else ["chrt", f"--{policy[0]}", str(policy[1])]  # as systemd would, at exec
            self.proc = subprocess.Popen(["ip", "netns", "exec", ns, *chrt, *self.argv], cwd=cwd, stdin=subprocess.DEVNULL,
                                         stdout=fh, stderr=subprocess.STDOUT, env=env, start_new_session=True)
        self.starts.append(time.time())
        self.pids.append(self.proc.pid)
        self.due, self.done = None, False

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def signal(self, sig: signal.Signals) -> None:
        if self.alive() and self.proc is not None:
            try:
                os.killpg(self.proc.pid, sig)
            except ProcessLookupError:
                pass


@dataclass
class Options:
    out: Path
    duration: float | None = None
    timeout: float | None = None
    """Give up this long after the start [s]; default the mission's duration plus 120 s."""
    kills: list[tuple[str, float]] = field(default_factory=list)
    """(unit, mission time [s]): SIGKILL that unit then."""
    skews: dict[str, float] = field(default_factory=dict)
    """Host directory -> clock offset [s] of every tether process on it (an unsynchronised host)."""
    partitions: list[tuple[str, str, float, float]] = field(default_factory=list)
    """(host A, host B, mission time [s], duration [s]): no packet passes between the two hosts'
    machines from then for that long (two sites cut apart: their routers)."""
    grace: float = 5.0
    replace: bool = False
    """Remove an earlier run's files from ``out`` (:data:`EARLIER`) instead of refusing it."""
    sitl: tuple[str, ...] | None = None
    """Start the software Crazyflies of the mission's ``udp://`` plants in the radio host's
    namespace before the units (as ``tether run --sitl`` does on one machine), with these extra
    simulator options; None: no simulator."""


def _mission(p: Plan) -> ms.Mission:
    leader_dir = p.deploy / "hosts" / next(h for h in p.hosts if h != "router")
    return ms.load(leader_dir / "mission.toml")


def _lost(runs: list[Running], epoch: float | None) -> list[inject.Event]:
    """A ``died`` event for every exit of a unit with a failure status or a signal while the run
    went on (the teardown's are not counted), as ``tether run``'s launcher reports its children."""
    out = []
    for r in runs:
        if r.unit.role == "start":
            continue
        for wall, rc in r.exits:
            if rc != 0:
                out.append(inject.Event(None if epoch is None else wall - epoch, r.unit.name, "died",
                                        inject.describe_exit(rc)))
    return out


def conclude(out: Path, runs: list[Running], m: ms.Mission, lost: list[inject.Event], ended: bool) -> int:
    """The rehearsal's exit status once the recorder has written ``out/run.npz``, as
    ``tether run``'s (:mod:`deploy.outcome`): the events every site logged that the run file lacks
    are merged into it (:mod:`deploy.sitelogs`), ``events.json`` lists what happened (``lost``: the
    units that died; the run's failsafes and divergences), and the status follows them (4 a process
    died, 3 a failsafe fired, 5 samples missing); :data:`~deploy.outcome.EXIT_FAILED` when the run
    did not end (``ended`` false)."""
    from deploy import sitelogs
    from tether import jsonout
    from tether.runfile import Run

    path = out / "run.npz"
    try:
        run = Run.load(path)
    except (OSError, ValueError, KeyError) as exc:
        log.error("no readable run file at %s (%s)", path, exc)
        return outcome.EXIT_FAILED
    agents, plants = [], []
    for r in runs:
        if r.unit.role == "agent" or r.unit.role in PLANT_ROLES:
            text = r.log_path.read_text(errors="replace")
            if r.unit.role == "agent":
                agents += sitelogs.agent_events(text, int(r.unit.name.rsplit("-", 1)[1]), m.dt)
            else:
                plants += sitelogs.plant_events(text, m.dt)
    run, added = sitelogs.merge(run, agents, plants)
    if added:
        run.save(path)
        log.warning("%d safety event(s) the recorder did not hear (a site cut off) merged into %s from the "
                    "units' logs", added, path)
    events = [*lost, *sitelogs.run_events(run, m.safety.max_formation_error)]
    safefs.write_file(out / "events.json", (jsonout.dumps([e.to_json() for e in events]) + "\n").encode())
    if events:
        log.warning("%d event(s) in this run (who, when, what, why):", len(events))
        for e in events:
            log.warning("  %s", e.line())
    return outcome.recorded(path, outcome.from_events(events) if ended else outcome.EXIT_FAILED, None)


def _epoch(log_text: str) -> float | None:
    """The start instant a process logged (``real time: tick 0 at <epoch>``)."""
    mt = re.search(r"real time: tick 0 at ([0-9.]+)", log_text)
    return float(mt.group(1)) if mt else None


EARLIER = ("rehearsal.json", "run.npz", "run.mcap", "events.json")
"""Files of ``--out`` that only a rehearsal writes: one there (or a unit log with something in it)
is an earlier run."""


def earlier_run(out: Path) -> list[str]:
    """The files of an earlier run in ``out`` (relative names; none if ``out`` does not exist). Only
    plain files count (never followed: a link in ``logs/`` is refused by :func:`_make_dirs`)."""
    found = [n for n in EARLIER if stat.S_ISREG(_lmode(out / n))]
    logs = out / "logs"
    if stat.S_ISDIR(_lmode(logs)):
        found += [f"logs/{p.name}" for p in sorted(logs.iterdir())
                  if p.name.endswith(".log") and stat.S_ISREG(_lmode(p)) and p.lstat().st_size > 0]
    return found


def _lmode(path: Path) -> int:
    try:
        return path.lstat().st_mode
    except FileNotFoundError:
        return 0


def _make_dirs(out: Path, runs: list[Running], rec_out: Path | None,
               replace: bool = False) -> tuple[Path, Path | None]:
    """Make ``out``, its ``logs/`` and every unit's log (empty), and the recorder unit's ``--out``
    ``rec_out``, through :mod:`tether.safefs` (following no link; a log that is a link or another
    user's file is refused): their real paths. ``replace``: remove an earlier run's files first
    (:func:`earlier_run`). :class:`RehearseError` naming the option and the file at fault, before
    anything starts."""
    from tether.node import os_error

    try:
        real = safefs.make_out(out)
        with safefs.Dir.open(real) as top, top.sub("logs") as logs:
            if replace:
                for name in earlier_run(real):
                    (logs if name.startswith("logs/") else top).remove(name.removeprefix("logs/"))
            for r in runs:
                logs.open_append(r.log_path.name).close()
    except OSError as exc:
        raise RehearseError(f"--out: {os_error(exc).removeprefix('--out: ')}") from None
    if rec_out is None:
        return real, None
    arg = "the recorder unit's --out"
    try:
        return real, safefs.make_out(rec_out, arg)
    except OSError as exc:
        raise RehearseError(f"{arg}: {os_error(exc).removeprefix(arg + ': ')}") from None


def rehearse(deploy: Path, opts: Options) -> int:
    """Run the rehearsal (see the module docstring); returns the exit status."""
    why = unavailable()
    if why is not None:
        print(f"error: tether rehearse {why}", file=sys.stderr)
        return 2
    try:
        unsafe = safefs.out_problem(opts.out)
    except OSError as exc:
        unsafe = f"cannot check {exc.filename or opts.out}: {exc.strerror}; give another directory"
    if unsafe is not None:
        print(f"error: --out: {unsafe}", file=sys.stderr)
        return 2
    old = earlier_run(opts.out)
    if old and not opts.replace:
        print(f"error: --out: {opts.out} holds an earlier run ({', '.join(old[:4])}"
              f"{', ...' if len(old) > 4 else ''}); give a fresh directory, or --replace to remove that run's files "
              "first", file=sys.stderr)
        return 2
    try:
        pl = plan(deploy)
        runs = []
        out_dir = recorder_out(pl.units)
        try:
            unsafe = safefs.out_problem(out_dir) if out_dir is not None else None
        except OSError as exc:
            unsafe = f"cannot check {exc.filename or out_dir}: {exc.strerror}; give another directory"
        if unsafe is not None:
            raise RehearseError(f"the recorder unit's --out: {unsafe}")
        logs = safefs.real_out(opts.out) / "logs"
        for host in opts.skews:
            if host not in pl.hosts:
                raise RehearseError(f"--skew {host}: no such host directory; use one of {', '.join(pl.hosts)}")
        for u in pl.units:
            runs.append(Running(u, command(u, opts.duration, opts.skews.get(u.host, 0.0)), logs / f"{u.name}.log"))
        for a, b, _, _ in opts.partitions:
            for host in (a, b):
                if host not in pl.hosts:
                    raise RehearseError(f"--partition {a}:{b}: no host directory {host}; use two of "
                                        f"{', '.join(pl.hosts)}")
            if pl.hosts[a] == pl.hosts[b]:
                raise RehearseError(f"--partition {a}:{b}: both hosts are one machine ({pl.hosts[a]}); cut two "
                                    "machines apart, e.g. the routers of two sites")
        names = {u.name for u in pl.units}
        for unit, _ in opts.kills:
            if unit not in names:
                raise RehearseError(f"--kill {unit}: no such unit; use one of {', '.join(sorted(names))}")
        mission = _mission(pl)
        duration = opts.duration if opts.duration is not None else mission.duration
        radio_host = next((u.host for u in pl.units if u.role == "radio"), None)
        if opts.sitl is not None:
            from deploy import sitl

            if radio_host is None:
                raise RehearseError(f"--sitl: the deployment has no radio unit (tether-radio-<k>): mission "
                                    f"{mission.name} flies no Crazyflie; drop --sitl")
            if bad := sitl.problems(mission, opts.sitl):
                raise RehearseError("--sitl: " + "; ".join(f"{f}: {why}" for f, why in bad))
    except RehearseError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        out, out_dir = _make_dirs(opts.out, runs, out_dir, opts.replace)
    except RehearseError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    net = Network()
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    record: dict[str, Any] = {"deploy": str(deploy), "namespaces": {}, "units": {}, "kills": [], "partitions": []}
    status = 1
    stopping = False
    ns_of: dict[str, str] = {}
    """Host directory -> its namespace."""
    sims: Any = None
    """The software Crazyflies (``--sitl``): a :class:`deploy.sitl.Sitl`."""

    def on_signal(signum: int, _frame: object) -> None:
        raise KeyboardInterrupt

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        net.create(pl.machines, pl.names)
        record["namespaces"] = {net.spaces[a]: {"address": a, "hosts": hs} for a, hs in pl.machines.items()}
        record["namespaces"][net.switch] = {"bridge": "br0"}
        if out_dir is not None:
            with safefs.Dir.open(out_dir) as rec:
                for name in ("run.npz", "run.mcap"):
                    rec.remove(name)
        ns_of.update({host: net.spaces[addr] for host, addr in pl.hosts.items()})
        router = [r for r in runs if r.unit.role == "router"]
        starter = next(r for r in runs if r.unit.name == "tether-start")
        others = [r for r in runs if r not in router and r is not starter]
        for r in router:
            r.spawn(ns_of[r.unit.host], env)
        deadline = time.monotonic() + ROUTER_UP
        while not all("listening on" in r.log_path.read_text(errors="replace") for r in router):
            if any(not r.alive() for r in router) or time.monotonic() > deadline:
                raise RuntimeError("the router did not come up:\n" + "\n".join(
                    r.log_path.read_text(errors="replace")[-2000:] for r in router))
            time.sleep(0.05)
        log.info("router up in %s", ", ".join(ns_of[r.unit.host] for r in router))
        if opts.sitl is not None and radio_host is not None:
            from deploy import sitl

            # at the radio unit's scheduling: the vehicles' clock must not starve behind the control loops
            policy = next(u.scheduling for u in pl.units if u.role == "radio")
            chrt = () if policy is None else ("chrt", f"--{policy[0]}", str(policy[1]))
            sims = sitl.start(mission, opts.sitl, logs, wrap=("ip", "netns", "exec", ns_of[radio_host], *chrt))
            record["sitl"] = {"host": radio_host, "pids": [p.pid for p in sims.procs.values()]}
            log.info("software Crazyflies up in %s", ns_of[radio_host])
        for r in others:
            r.spawn(ns_of[r.unit.host], env)
        starter.spawn(ns_of[starter.unit.host], env)
        log.info("%d units started in %d namespaces; %s waits for every process", len(others), len(pl.machines),
                 starter.unit.name)
        epoch: float | None = None
        limit = time.monotonic() + (opts.timeout if opts.timeout is not None else duration + 180.0)
        kills = sorted(opts.kills, key=lambda x: x[1])
        cuts = sorted(opts.partitions, key=lambda x: x[2])
        heals: list[tuple[float, str, str, dict[str, Any]]] = []
        while True:
            now = time.monotonic()
            for r in runs:
                if r.proc is None or r.done or r.due is not None:
                    continue
                rc = r.proc.poll()
                if rc is None:
                    continue
                r.exits.append((time.time(), rc))
                failed = rc != 0
                again = r.unit.restart == "always" or (r.unit.restart == "on-failure" and failed)
                if again and not stopping:
                    r.due = now + r.unit.restart_sec
                    log.warning("%s exited with status %d: restarting in %g s (Restart=%s)", r.unit.name, rc,
                                r.unit.restart_sec, r.unit.restart)
                else:
                    r.done = True
                    (log.warning if failed else log.info)("%s exited with status %d", r.unit.name, rc)
            for r in runs:
                if r.due is not None and now >= r.due:
                    r.spawn(ns_of[r.unit.host], env)
                    log.info("%s restarted", r.unit.name)
            if epoch is None:
                epoch = next((e for r in others if (e := _epoch(r.log_path.read_text(errors="replace"))) is not None),
                             None)
                if epoch is not None:
                    record["epoch"] = epoch
            if epoch is not None:
                while kills and time.time() >= epoch + kills[0][1]:
                    unit, at = kills.pop(0)
                    victim = next(r for r in runs if r.unit.name == unit)
                    victim.signal(signal.SIGKILL)
                    record["kills"].append({"unit": unit, "at": at, "wall": time.time(), "mission_time": time.time() - epoch})
                    log.warning("--kill %s@%g: SIGKILL at mission time %.3f s", unit, at, time.time() - epoch)
                while cuts and time.time() >= epoch + cuts[0][2]:
                    a, b, at, span = cuts.pop(0)
                    net.cut(pl.hosts[a], pl.hosts[b])
                    entry = {"hosts": [a, b], "at": at, "for": span, "cut_wall": time.time(),
                             "cut_mission_time": time.time() - epoch}
                    record["partitions"].append(entry)
                    heals.append((epoch + at + span, pl.hosts[a], pl.hosts[b], entry))
                    log.warning("--partition %s:%s: cut at mission time %.3f s", a, b, time.time() - epoch)
                for due in [x for x in heals if time.time() >= x[0]]:
                    heals.remove(due)
                    net.heal(due[1], due[2])
                    due[3].update(heal_wall=time.time(), heal_mission_time=time.time() - epoch)
                    log.warning("--partition %s: healed at mission time %.3f s", ":".join(due[3]["hosts"]),
                                time.time() - epoch)
            if starter.done and starter.exits[-1][1] != 0:
                log.error("%s failed (exit %d): %s", starter.unit.name, starter.exits[-1][1],
                          starter.log_path.read_text(errors="replace")[-1500:])
                break
            if all(r.done for r in others) and starter.done:
                break
            if epoch is not None and time.time() > epoch + duration + END_GRACE:
                late = [r.unit.name for r in others if not r.done]
                log.error("%s still running %g s after the mission's end (restarted after the run, waiting for a "
                          "start that will not come?): stopping", ", ".join(late), END_GRACE)
                break
            if now > limit:
                log.error("the run did not end in time (--timeout)")
                break
            time.sleep(0.05)
        stopping = True
        lost = _lost(runs, epoch)
        ended = starter.done and starter.exits[-1][1] == 0 and all(r.done for r in others)
        recorded = out_dir is not None and (out_dir / "run.npz").exists()
        if recorded and out_dir is not None and out_dir != out:
            for name in ("run.npz", "run.mcap"):
                _copy_in(out_dir, name, out)
        status = conclude(out, runs, mission, lost, ended) if recorded else outcome.EXIT_FAILED
    except KeyboardInterrupt:
        log.warning("interrupted: tearing down")
        status = 130
    except RuntimeError as exc:
        log.error("%s", exc)
        status = 1
    finally:
        stopping = True
        for sig in previous:  # a second Ctrl-C must not cut the teardown short
            signal.signal(sig, signal.SIG_IGN)
        try:
            _stop_all(runs, opts.grace)
            if sims is not None:
                record["sitl"]["exits"] = sims.stop(opts.grace)
            net.destroy()
        finally:
            for sig, h in previous.items():
                signal.signal(sig, h)
        left = namespaces_of(os.getpid())
        record["units"] = {r.unit.name: {"host": r.unit.host, "namespace": ns_of.get(r.unit.host),
                                         "argv": r.argv, "starts": r.starts, "pids": r.pids, "exits": r.exits,
                                         "restart": r.unit.restart} for r in runs}
        record["left_behind"] = left
        safefs.write_file(out / "rehearsal.json", (json.dumps(record, indent=2) + "\n").encode())
        if left:
            log.error("namespaces left behind: %s", left)
            status = status or 1
    log.info("rehearsal ended: status %d (%s)", status, opts.out)
    return status


def _copy_in(src: Path, name: str, dst: Path) -> None:
    """Copy file ``name`` of directory ``src`` (if there) into directory ``dst``, both real paths:
    read following no link, written under an exclusive temporary name and renamed over ``name``
    (an entry there, a link included, is replaced, never written through). Blocks for the copy."""
    from tether.node import os_error

    try:
        with safefs.Dir.open(src) as s, safefs.Dir.open(dst) as d:
            try:
                fd = os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC, dir_fd=s.fd)
            except FileNotFoundError:
                return
            with open(fd, "rb") as fin:
                if not stat.S_ISREG(os.fstat(fin.fileno()).st_mode):
                    raise RuntimeError(f"{src / name} is not a plain file; nothing copied")
                tmp = f".{name}.{secrets.token_hex(6)}.part"
                with d.open_new(tmp) as fout:
                    shutil.copyfileobj(fin, fout, 1 << 20)
                d.rename(tmp, name)
    except OSError as exc:
        raise RuntimeError(f"copying {src / name} into {dst}: {os_error(exc)}") from None


def _stop_all(runs: list[Running], grace: float) -> None:
    live = [r for r in runs if r.alive()]
    for r in live:
        r.signal(signal.SIGTERM)
    deadline = time.monotonic() + grace
    for r in live:
        if r.proc is None:
            continue
        try:
            r.proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            r.signal(signal.SIGKILL)
            r.proc.wait()
        if not r.exits or r.exits[-1][0] < r.starts[-1]:
            r.exits.append((time.time(), r.proc.returncode))


# --------------------------------------------------------------------------- command line
def _kill(text: str) -> tuple[str, float]:
    unit, sep, at = text.rpartition("@")
    try:
        t = float(at)
    except ValueError:
        t = float("nan")
    if not sep or not unit or not (t >= 0 and t < float("inf")):
        raise argparse.ArgumentTypeError(f"{text!r} is not UNIT@T (a unit name and a mission time >= 0 [s]), "
                                         "e.g. tether-agent-2@5")
    return unit.removesuffix(".service"), t


def _skew(text: str) -> tuple[str, float]:
    from tether.clock import check_skew

    host, sep, value = text.partition("=")
    try:
        s = float(value)
    except ValueError:
        s = float("nan")
    why = check_skew(s, "the skew")
    if not sep or not host or why is not None:
        raise argparse.ArgumentTypeError(f"{text!r} is not HOST=S (a host directory and a clock offset [s]), e.g. "
                                         f"agent-2=+0.03" + (f"; {why}" if sep and host and why else ""))
    return host, s


def _partition(text: str) -> tuple[str, str, float, float]:
    pair, sep, when = text.rpartition("@")
    a, colon, b = pair.partition(":")
    at, plus, span = when.partition("+")
    try:
        t, d = float(at), float(span)
    except ValueError:
        t = d = float("nan")
    if not (sep and colon and plus and a and b and a != b and 0 <= t < float("inf") and 0 < d < float("inf")):
        raise argparse.ArgumentTypeError(f"{text!r} is not HOST_A:HOST_B@T+D (two host directories, a mission time "
                                         ">= 0 and a duration > 0 [s]), e.g. router-ground:router-field@6+4")
    return a, b, t, d


def _seconds(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (v > 0 and v < float("inf")):
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds > 0")
    return v


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("deploy", help="a deployment written by tether deploy-gen (its --out)")
    p.add_argument("--out", required=True, help="directory for the run file, the units' logs and rehearsal.json")
    p.add_argument("--replace", action="store_true",
                   help="--out may hold an earlier run: remove its files first (without it, such an --out is refused)")
    p.add_argument("--duration", type=_seconds, default=None, help="override the mission's duration [s]")
    p.add_argument("--timeout", type=_seconds, default=None,
                   help="give up this long after the units start [s] (default: the duration + 180 s)")
    p.add_argument("--kill", action="append", type=_kill, default=[], metavar="UNIT@T",
                   help="SIGKILL a unit's process at mission time T [s] (its Restart= then applies); repeatable")
    p.add_argument("--skew", action="append", type=_skew, default=[], metavar="HOST=S",
                   help="every tether process of host directory HOST runs S seconds ahead (--clock-skew): an "
                        "unsynchronised host; repeatable")
    p.add_argument("--partition", action="append", type=_partition, default=[], metavar="HOST_A:HOST_B@T+D",
                   help="no packet passes between the machines of host directories HOST_A and HOST_B from mission "
                        "time T for D seconds (two sites cut apart); repeatable")
    p.add_argument("--sitl", action="store_true",
                   help="start the software Crazyflies of the mission's udp:// plants in the radio host's namespace "
                        "first (python -m plant.cfsim, as tether run --sitl does)")
    p.add_argument("--sitl-args", default="", metavar="ARGS",
                   help="extra options of every software Crazyflie, one string (e.g. \"--noise 0.1 --seed 2\"); "
                        "with --sitl")


def run_args(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s rehearse: %(message)s")
    if args.sitl_args and not args.sitl:
        print("error: --sitl-args: give it with --sitl", file=sys.stderr)
        return 2
    return rehearse(Path(args.deploy), Options(out=Path(args.out), duration=args.duration, timeout=args.timeout,
                                               kills=list(args.kill), skews=dict(args.skew),
                                               partitions=list(args.partition), replace=args.replace,
                                               sitl=tuple(shlex.split(args.sitl_args)) if args.sitl else None))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="tether rehearse", description=__doc__.splitlines()[0])
    add_arguments(p)
    return run_args(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
