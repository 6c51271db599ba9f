"""The run's processes: their command lines, their logs, their start and their stop.

Each child is a process of its own (``subprocess``: nothing is forked after Zenoh is loaded) in a
session (process group) of its own, its stderr in ``DIR/logs/<role>-<id>.log``; it stops when the
launcher is gone. The recorder is stopped last, so that it holds what the others sent.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from deploy import localtls
from deploy.options import MESH_LINK_TIME, LaunchOptions, Pace, record_batch, write_grace
from deploy.relay import Relay
from tether import mission as ms
from tether import safefs
from tether import transport as tp
from tether import wire

log = logging.getLogger("tether")


LOG_RESERVE = 4 * 2**20
"""Free space [bytes] a run's ``--out`` must have beyond the run file's estimate, for its logs."""

HANDOVER = "(rx: (handover: app), acc: (handover: app), net: (handover: app), tx: (handover: app))"
"""``ZENOH_RUNTIME`` of every child: Zenoh's runtime threads handed over to one thread per child
(:attr:`LaunchOptions.handover_runtime`)."""


def child_env(o: LaunchOptions) -> dict[str, str]:
    """The environment every child starts with: the launcher's, one BLAS thread, and Zenoh's runtime
    threads handed over (:attr:`LaunchOptions.handover_runtime`)."""
    env = dict(os.environ)
    # numpy works on 2- and 3-vectors in every role: one BLAS thread each (a pool of idle
    # OpenBLAS threads per process costs memory and wake-ups, never speed, on these sizes)
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(var, "1")
    if o.handover_runtime:
        env.setdefault("ZENOH_RUNTIME", HANDOVER)
    return env


@dataclass
class Child:
    """One started process of the run."""

    role: str
    node_id: int
    proc: subprocess.Popen
    log_path: Path
    status: int | None = None

    @property
    def name(self) -> str:
        return f"{self.role}/{self.node_id}"

    def error(self) -> str | None:
        """The last error line of its log (``... ERROR role/id: failed: ...``), if any."""
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return None
        for line in reversed(lines):
            if " ERROR " in line:
                return line.split(": ", 1)[-1]
        return None

    def tail(self, lines: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"


@dataclass
class Launch:
    """The processes of one run: their command lines, logs, start and stop."""

    mission_path: Path
    mission: ms.Mission
    opts: LaunchOptions
    """Resolved (:func:`deploy.options.resolve`)."""
    pace: Pace
    """How the run keeps time: what the children's command lines say of the clock."""
    children: list[Child] = field(default_factory=list)
    relays: dict[tuple[str, int], Relay] = field(default_factory=dict)
    """Processes whose link to the router goes through a relay (partition faults)."""
    logs: dict[tuple[str, int], BinaryIO] = field(default_factory=dict)
    """Every child's log file, opened by :meth:`open_logs` before any process starts."""

    def open_logs(self) -> None:
        """Check that ``--out`` can hold the run, then create ``logs/`` and every child's log file,
        before any process starts. Raises :class:`~tether.mission.MissionError` naming ``--out``
        (exit status 2): the file that could not be made and why (ENOSPC, EACCES, EROFS...), or
        the free space against the run file's estimate (:func:`tether.checks.run_bytes`)."""
        from tether import checks
        from tether.node import os_error

        out = self.opts.out
        try:
            free = shutil.disk_usage(out).free
        except OSError as exc:
            raise ms.MissionError("tether run", [("--out", f"cannot use {out}: {os_error(exc)}")]) from None
        need = checks.run_bytes(self.mission) + LOG_RESERVE
        if free < need:
            raise ms.MissionError("tether run", [("--out", (
                f"{out} has {free / 2**20:.3g} MiB free, but the run needs about {need / 2**20:.3g} MiB "
                f"(the run file's arrays and {LOG_RESERVE // 2**20} MiB of logs); free space on its file "
                "system, give another --out, or shorten the run (--duration)"))])
        try:
            with safefs.Dir.open(out) as top, top.sub("logs") as logs:
                for role, nid in self.members():
                    self.logs[role, nid] = logs.open_log(f"{role}-{nid}.log")
        except OSError as exc:
            self.close_logs(remove=True)
            raise ms.MissionError("tether run", [("--out", f"cannot create the run's logs: {os_error(exc)}; "
                                                           "nothing was started")]) from None

    def close_logs(self, remove: bool = False) -> None:
        """Close the log files not handed to a process (and ``remove`` them: none was used)."""
        for fh in self.logs.values():
            fh.close()
            if remove:
                Path(fh.name).unlink(missing_ok=True)
        self.logs.clear()

    @property
    def keys(self) -> wire.Keys:
        """The run's keys, in ``--ns`` (by default the mission's name)."""
        return wire.Keys(self.opts.ns or self.mission.name)

    def members(self) -> list[tuple[str, int]]:
        """Every process of the run, as ``(role, id)``, in the order they start."""
        m = self.mission
        if self.opts.colocate_plants:  # each plant inside its agent
            return [("leader", m.leader.id), *[("agent", a) for a in m.agent_ids], ("recorder", 0)]
        if m.payload is not None or self.opts.shared_plants:  # one world hosts every vehicle (and the payload)
            return [("leader", m.leader.id), *[("agent", a) for a in m.agent_ids], ("world", 0), ("recorder", 0)]
        return [("leader", m.leader.id), *[(r, a) for a in m.agent_ids for r in ("agent", "plant")], ("recorder", 0)]

    def spawn(self, router: str, sec: localtls.Security | None = None) -> None:
        """Start every member, each in a session (process group) of its own, its output to its log;
        ``router``: the launcher's router endpoint, ``sec``: the run's identities (None: --insecure)."""
        if not self.logs:
            self.open_logs()
        env = child_env(self.opts)
        hosted = self.radio_groups()
        for role, nid in self.members():
            if role == "plant" and nid in hosted:
                if hosted[nid][0] == nid:
                    self.spawn_radio_host(hosted[nid], router, sec, env)
                continue
            cmd = self.argv(role, nid, router, sec)
            fh = self.logs.pop((role, nid))
            path = Path(fh.name)
            with fh:
                proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT,
                                        env=env, start_new_session=True)
            self.children.append(Child(role, nid, proc, path))

    def radio_groups(self) -> dict[int, tuple[int, ...]]:
        """Crazyflies that share a dongle with another (:func:`plant.radio.dongles`), by agent id: the
        ids of its dongle's vehicles. They are flown by one radio host process (:mod:`cli.radio`)."""
        from plant import radio

        o = self.opts
        if o.colocate_plants or o.shared_plants or self.mission.payload is not None or o.wrap:
            return {}
        cfs = [(a.id, a.plant.uri) for a in self.mission.agents if isinstance(a.plant, ms.CrazyfliePlant)]
        return {aid: d.agents for d in radio.dongles(cfs) if len(d.agents) > 1 for aid in d.agents}

    def spawn_radio_host(self, ids: tuple[int, ...], router: str, sec: localtls.Security | None,
                         env: dict[str, str]) -> None:
        """Start one radio host for the plants ``ids``: each keeps its command line (its identity, its
        endpoints) and its log; the process is each plant's :class:`Child`."""
        cmd = [sys.executable, "-m", "cli.radio"]
        fhs = [self.logs.pop(("plant", nid)) for nid in ids]
        if len(ids) > 1:
            cmd += ["--log-fds", ",".join(str(fh.fileno()) for fh in fhs[1:])]
        for nid in ids:
            full = self.argv("plant", nid, router, sec)
            cmd += ["--", *full[full.index("plant") + 1:]]  # its options, after python -m cli plant
        try:
            proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=fhs[0], stderr=subprocess.STDOUT, env=env,
                                    start_new_session=True, pass_fds=[fh.fileno() for fh in fhs[1:]])
        finally:
            for fh in fhs:
                fh.close()
        for nid, fh in zip(ids, fhs):
            self.children.append(Child("plant", nid, proc, Path(fh.name)))

    def argv(self, role: str, nid: int, router: str, sec: localtls.Security | None) -> list[str]:
        """The command line of member ``role/nid`` (see :meth:`spawn`)."""
        o = self.opts
        cmd = [sys.executable, "-m", "cli", role, "--mission", str(self.mission_path), *self.pace.child_args(o),
               "--ns", self.keys.ns, "--parent-pid", str(os.getpid()),
               "--stall-timeout", str(o.stall_timeout), "--start-timeout", repr(o.start_timeout),
               "--lease", str(o.lease), "--log-level", o.log_level]
        if o.duration is not None:
            cmd += ["--duration", repr(o.duration)]
        if o.rt_priority is not None:  # the recorder is no control loop: normal policy (it writes the run at the end)
            cmd += ["--rt-priority", str(0 if role == "recorder" else o.rt_priority)]
        if role in ("agent", "plant"):
            cmd += ["--id", str(nid)]
        if o.colocate_plants and role in ("agent", "recorder"):
            cmd += ["--colocate-plant"]
        if o.colocate_plants and role in ("agent", "leader"):  # the recorder hears records alone
            cmd += ["--record-batch", str(record_batch(o))]
        if role == "recorder":
            cmd += ["--out", str(o.out)]
            if o.live is not None:
                cmd += ["--live", str(o.live)]
            if not o.mcap:
                cmd += ["--no-mcap"]
        skew = sum(f.skew for f in o.faults if f.kind == "skew" and f.member(self.mission) == (role, nid))
        if skew:
            cmd += ["--clock-skew", repr(skew)]
        cmd += self.link_args(role, nid, router, sec)
        vehicle = role in ("agent", "plant")
        return [*o.wrap[nid], *cmd] if vehicle and nid in o.wrap else cmd

    def link_args(self, role: str, nid: int, router: str, sec: localtls.Security | None) -> list[str]:
        """How member ``role/nid`` joins the run's network: its Zenoh mode, endpoints and identity."""
        o = self.opts
        vehicle = role in ("agent", "plant")
        endpoint = o.vehicle_connect.get(nid, router) if vehicle else router
        if (role, nid) in self.relays:
            endpoint = self.relays[role, nid].endpoint
            if sec is not None:  # the relay forwards bytes: TLS passes through it end to end
                endpoint = "tls/" + endpoint.split("/", 1)[1]
        if sec is not None:
            listen = None if o.network == "star" else f"tls/127.0.0.1:{tp.free_tcp_port()}"
            cmd = ["--zenoh-config", str(sec.child(role, nid, endpoint, listen))]
        elif o.network == "star":
            cmd = ["--zenoh-mode", "client", "--connect", endpoint]
        else:
            cmd = ["--zenoh-mode", "peer", "--connect", endpoint, "--listen", tp.loopback_endpoint(tp.free_tcp_port())]
        if o.network == "mesh":  # its token once linked to every other member (tether/node.py)
            others = len(self.members()) - 1
            cmd += ["--mesh-peers", str(others), "--connect-timeout", repr(max(10.0, MESH_LINK_TIME * others))]
        return cmd

    def poll(self) -> list[Child]:
        """Children that have exited since the last poll."""
        ended = []
        for c in self.children:
            if c.status is None and (rc := c.proc.poll()) is not None:
                c.status = rc
                ended.append(c)
        return ended

    def terminate(self, grace: float = 5.0, recorder_grace: float | None = None) -> None:
        """SIGTERM every live child but the recorder, SIGKILL those still alive after ``grace`` seconds;
        then the recorder, which writes ``run.npz`` and ``run.mcap`` when stopped, within
        ``recorder_grace`` (default: :func:`write_grace` of the whole mission). The recorder goes last,
        once the others have gone: what they sent before (a vehicle's LANDED, the moment before a run
        ends) has reached it, and it decodes what waits in its queues before writing."""
        if recorder_grace is None:
            recorder_grace = write_grace(self.mission, self.mission.steps)
        live = [c for c in self.children if c.proc.poll() is None]
        for group, bound in (([c for c in live if c.role != "recorder"], grace),
                             ([c for c in live if c.role == "recorder"], max(grace, recorder_grace))):
            for c in group:
                c.proc.send_signal(signal.SIGTERM)
                c.proc.send_signal(signal.SIGCONT)  # a frozen process must run to handle its SIGTERM
            t0 = time.monotonic()
            for c in group:
                try:
                    c.proc.wait(max(0.0, t0 + bound - time.monotonic()))
                except subprocess.TimeoutExpired:
                    if c.role == "recorder":
                        log.error("the recorder did not finish writing the run files within %.0f s of the stop: "
                                  "killed (run.npz is written first; run.mcap may be missing)", bound)
                    c.proc.kill()
                    c.proc.wait()
        self.poll()


class LaunchFailed(RuntimeError):
    """The run cannot go on (a process did not come up, a lockstep run lost one or stalled): exit 1."""
