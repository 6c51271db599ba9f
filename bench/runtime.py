"""Figures of the distributed runtime, each beside a bare Zenoh baseline measured in the same run.

    .venv/bin/python bench/runtime.py                        # every case (about 7 minutes)
    .venv/bin/python bench/runtime.py --cases lockstep --repeats 5
    .venv/bin/python bench/runtime.py --cases colocate --repeats 3 --colocate-windows 16:4 16:8 32:16 [--colocate-mesh]
    .venv/bin/python bench/runtime.py --cases network --repeats 2 --network-sizes 4 8 16 24 32
    .venv/bin/python bench/runtime.py --cases scale --sizes 4 8 16 32 --scale-repeats 2
    .venv/bin/python bench/runtime.py --cases latency cpu --json /tmp/bench.json
    .venv/bin/python bench/runtime.py --profile agent:1 [--profile-clock realtime --mission FILE]

The baseline (``bench/baseline_node.py``, started and measured by ``bench/baseline.py``; process
figures from ``/proc`` by ``bench/procstat.py``) runs the same processes with the same keys, payload
sizes, QoS, rates, star topology (router session in the launcher's place, every other process a
client) and ``ZENOH_RUNTIME`` handover as ``tether run``, but with trivial work. Cases
(``docs/benchmarks.md`` has the method, the figures and what they mean):

1. ``lockstep``: simulated seconds per wall second of ``tether run MISSION --clock lockstep``
   (section4: N = 4, 100 Hz), from the launcher's "ran X s of mission time in Y s of wall time";
   beside it the bare baseline, two bare experiments (plants co-located in their agents; and also
   the recorder's samples batched per 4 ticks with a window of 16), the in-process reference
   simulator, and CPU per tick by role and thread kind (asyncio main / callback / Zenoh runtime).
   ``colocate`` compares the structures (plant processes, co-located, batched records, windows,
   ``--colocate-mesh``) each beside its bare baseline; ``network`` flies rings of N agents as a
   star and as a peer mesh (speed, start-up, the whole command), which sets
   ``deploy.options.MESH_MAX_AGENTS``; neither runs unless named.
2. ``scale``: real time at 50 Hz, N = 4, 8, 16 (32 if 16 holds) agents on a ring
   (``bench/missions.py``), stepping up until a size does not hold; late ticks from the run file's
   ``runtime.late``; total CPU of every process (launcher/router included) from
   ``/proc/<pid>/stat`` over the mission window, beside the baseline's at the same N.
3. ``latency``: real time, N = 8, 100 Hz. A probe process (a Zenoh client of the same router)
   subscribes to every plant's and agent's state key and to the start message, and stamps each
   arrival on CLOCK_MONOTONIC in its subscriber callback. ``plant``: arrival - (t0 + k h), t0 the
   start epoch mapped to CLOCK_MONOTONIC exactly as the nodes' ``RealtimeClock`` maps it (the
   plant's timer, its work before ``put``, one hop). ``relay``: arrival of agent i's relay of plant
   i's sample k minus arrival of that sample (one hop more, through the agent's receive path and
   back out; no clock assumption). The baseline's payload also carries its send time (put ->
   callback alone). Plus the share of relays arriving after a phase of the period, and
   ``links.age``/``runtime.meas_age``.
4. ``cpu``: CPU, VmRSS, PSS and USS per agent process, tether vs baseline, from the real-time runs
   of cases 2 and 3 that held their rate and were not disturbed (or one N = 8, 50 Hz pair).

Every run is preceded by a wait for the machine to be quiet (``--quiet-below``), and the CPU that
other users took during each run is measured (``/proc/stat`` minus our processes) and printed;
runs where it exceeds 50 % of a core are flagged NOISY and left out of the medians when a quiet
run exists. Figures are medians over runs and over processes of a role.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import queue
import re
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from bench import missions  # noqa: E402
from bench.baseline import (  # noqa: E402
    AGENT_PHASE, LOOP, PY, START_LEAD, WINDOW, example_message, launcher_env, probe_ready, probe_stats,
    run_baseline, spawn_probe,
)
from bench.procstat import (  # noqa: E402
    Proc, Result, Window, children_of, cmdline, med, pct, ratio, read_lines, reap, wait_quiet,
)
from tether import mission as ms  # noqa: E402
from tether import catalog  # noqa: E402
from tether import evloop  # noqa: E402
from tether import jsonout  # noqa: E402
from tether import handoff  # noqa: E402
from tether import runfile  # noqa: E402
from tether import transport as tp  # noqa: E402
from tether import wire  # noqa: E402

if TYPE_CHECKING:
    from tether.clock import ClockKind


# =========================================================================== tether runs
def _tether_cmd() -> list[str]:
    exe = Path(PY).parent / "tether"
    return [str(exe)] if exe.exists() else [PY, "-m", "cli"]


def run_tether(mission_path: Path, m: ms.Mission, clock: str, duration: float, work: Path,
               probe: bool = False, timeout: float = 300.0, tree: Path | None = None,
               extra: tuple[str, ...] = (), secure: bool = True, mcap: bool = True) -> Result:
    """``tether run MISSION --clock CLOCK --duration S --quiet [EXTRA]`` (and ``--insecure`` unless
    ``secure``; ``--no-mcap`` unless ``mcap``: the recorder writes ``run.mcap`` after the last tick,
    outside the measured window, but in the whole command's time), measured from outside.
    ``tree``: another checkout of tether (``bench/ab.py``'s base),
    run as ``python -m cli`` from inside it, so that the launcher and every process it starts (``-m``
    puts the working directory first on the path, and the children inherit it) import that tree and
    not the installed one; :attr:`Result.cwds` says where each process ran."""
    out = work / f"tether-{clock}-{m.n}-{time.monotonic_ns()}"
    cmd = [*(_tether_cmd() if tree is None else [PY, "-m", "cli"]), "run", str(mission_path), "--out", str(out),
           "--clock", clock, "--duration", repr(duration), "--quiet", *(() if mcap else ("--no-mcap",)), *extra,
           *(() if secure else ("--insecure",))]
    res = Result("tether", m.n, clock, m.rate)
    probe_proc = None
    probe_out = out.with_suffix(".probe.json")
    if probe:
        # the probe starts before the run, on an endpoint the launcher listens on (it connects as soon
        # as the launcher's router is up), so that it has subscribed long before the start message
        # (started once the first child was seen, it lost that race under load: 'no probe data')
        ep = tp.loopback_endpoint(tp.free_tcp_port())
        cmd += ["--listen", ep]
        probe_proc = spawn_probe(ep, m.name, m.rate, "tether", m.n, int(round(duration * m.rate)), probe_out,
                                  wait=False)
    t_start = time.monotonic()
    env = launcher_env()
    if tree is not None:
        env["PYTHONPATH"] = str(tree)
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
                         cwd=tree or REPO)
    try:
        if probe_proc is not None:
            probe_ready(probe_proc)
        log, t_ran = _watch(p, res, clock, timeout, t_start, probe_proc)
        rc = res.status = p.wait(timeout=60)
        exited = time.monotonic()
        res.command_s, res.end_s = exited - t_start, exited - t_ran
        if rc != 0:
            res.ok, res.why = False, f"tether run exited {rc}: " + "".join(log[-5:])
    finally:
        if p.poll() is None:
            p.terminate()
            p.wait()
        if probe_proc is not None:
            reap(probe_proc, 30.0)
    _read_run_file(out / "run.npz", res, m, duration)
    if probe and probe_out.exists():
        res.probe = json.loads(probe_out.read_text())
    return res


def _watch(p: subprocess.Popen[str], res: Result, clock: str, timeout: float, t_start: float,
           probe_proc: subprocess.Popen[str] | None) -> tuple[list[str], float]:
    """Follow the launcher's log until it closes: once every process is up, measure them all over
    the mission's window (opened at tick 0, closed at the "ran ..." line). Blocks until the launcher
    closes its stderr; returns the log and the monotonic time of the "ran ..." line."""
    lines: queue.Queue[str | None] = queue.Queue()
    threading.Thread(target=read_lines, args=(p.stderr, lines), daemon=True).start()
    log: list[str] = []
    timer: threading.Timer | None = None
    window: Window | None = None
    t_ran = float("nan")
    deadline = time.monotonic() + timeout
    while True:
        try:
            line = lines.get(timeout=0.02)
        except queue.Empty:
            if time.monotonic() > deadline:
                raise TimeoutError(f"tether run did not finish in {timeout} s") from None
            continue
        if line is None:
            return log, t_ran
        log.append(line)
        if "processes are up after" in line:
            res.startup_s = time.monotonic() - t_start
            _measured(p.pid, res, probe_proc)
            t_up = time.monotonic()
            lead = START_LEAD if clock == "realtime" else 0.0
            window = Window(res.procs)
            timer = threading.Timer(max(0.0, t_up + lead - time.monotonic()), window.open)
            timer.start()
        mo = re.search(r"ran (\S+) s of mission time in (\S+) s of wall time", line)
        if mo:
            if timer is None or window is None:
                raise RuntimeError("tether run reported its end before its processes were up: no measured window")
            timer.join()
            window.close(res)
            res.mission_s, res.wall_s = float(mo[1]), float(mo[2])
            t_ran = time.monotonic()


def _measured(launcher: int, res: Result, probe_proc: subprocess.Popen[str] | None) -> None:
    """Add the launcher, every process it started (role and id from its command line; its working
    directory to :attr:`Result.cwds`) and the probe to the processes ``res`` measures."""
    for c in children_of(launcher):
        args = cmdline(c)
        if "cli" in args:
            role = args[args.index("cli") + 1]
            nid = int(args[args.index("--id") + 1]) if "--id" in args else 0
            res.procs.append(Proc(c, role, nid))
            with contextlib.suppress(OSError):
                res.cwds.add(os.readlink(f"/proc/{c}/cwd"))
    res.procs.append(Proc(launcher, "launcher", 0))
    if probe_proc is not None:
        res.procs.append(Proc(probe_proc.pid, "probe", 0))


def _read_run_file(run_file: Path, res: Result, m: ms.Mission, duration: float) -> None:
    """Fill ``res`` from the run's ``run.npz``, if it was written: samples recorded, the share of late
    ticks (real time) and the ages of the data used."""
    if not run_file.exists():
        return
    with np.load(run_file) as z:
        meta = runfile.decode_meta(str(z["meta"]))
        res.complete = f"{meta.samples_recorded}/{meta.samples_expected}"
        late = z["late"] if "late" in z.files else None
        if late is not None and res.clock == "realtime":
            per_agent = np.nanmax(np.where(np.isfinite(late), late, -1), axis=0)
            per_agent = np.maximum(per_agent, 0)
            steps = int(round(duration * m.rate)) + 1
            res.late = float(per_agent.sum() / (m.n * steps))
            res.late_max = float(per_agent.max() / steps)
        for name in ("link_age", "meas_age"):
            if name in z.files:
                age = z[name]
                setattr(res, name, age[np.isfinite(age)])


# =========================================================================== helpers
def compile_tree(tree: Path = REPO) -> int:
    """Compile the tree's bytecode into ``__pycache__``, as ``pip install`` does for a package: the
    baseline's libraries are compiled, and a process that compiles tether's modules at every start
    (``PYTHONDONTWRITEBYTECODE``, or a tree never imported) pays the compiler's CPU and keeps its
    memory (1.6 MiB more RSS per agent, measured). Returns how many files were compiled."""
    import compileall
    import io
    packages = ("agent", "cli", "deploy", "leader", "netem", "plant", "recorder", "sim", "tether")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        for pkg in packages:
            compileall.compile_dir(str(tree / pkg), quiet=0)
    return sum(1 for line in out.getvalue().splitlines() if line.startswith("Compiling"))


def say(text: str = "") -> None:
    print(text, flush=True)


QUIET = {"limit": 0.5, "timeout": 60.0}


def settle() -> None:
    """Before a run: wait for the machine to be quiet (see :func:`wait_quiet`); say so if it is not."""
    busy = wait_quiet(QUIET["limit"], QUIET["timeout"])
    if busy > QUIET["limit"]:
        say(f"   (the machine is busy with other work: {busy:.2f} cores in use before this run)")


NOISY = 50.0
"""A run during which other users took more than this much CPU [% of one core] is flagged noisy."""


def _quiet(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows whose runs were not noisy (both tether's and the baseline's), or all if none was quiet."""
    quiet = [r for r in rows if max(r["foreign_pct"]) < NOISY]
    return quiet or rows


def mission_file(work: Path, n: int, rate: float, duration: float) -> tuple[Path, ms.Mission]:
    path = work / f"ring{n}-{rate:g}hz.toml"
    return path, missions.write(path, n, rate=rate, duration=duration, topology="ring")


# =========================================================================== cases
ROLES = ("launcher", "leader", "agent", "plant", "recorder")


def _per_tick(res: Result, ticks: float, roles: tuple[str, ...] = ROLES) -> dict[str, Any]:
    """CPU per tick [us] by role (median process; NaN for a role that did not run) and by thread
    kind, and the total."""
    f = 1e4 * res.window_s / ticks  # % of one core over the window -> us per tick
    out: dict[str, Any] = {"total_us": res.total_cpu_pct() * f}
    for ro in roles:
        th = res.thread_pct(ro)
        out[ro] = {"us": med(res.cpu_pct(ro)) * f, **{k: v * f for k, v in th.items()}}
    return out


def _role_table(tether: dict[str, Any], base: dict[str, Any], title: str) -> None:
    """Print per-role CPU per tick, tether vs baseline, split by thread kind."""
    say(f"   {title}")
    say(f"   {'role':9} {'tether us':>10} {'(main/cb/zenoh)':>17} {'baseline us':>12} {'(main/cb/zenoh)':>17} {'ratio':>6}")
    for ro in ROLES:
        t, b = tether[ro], base[ro]
        say(f"   {ro:9} {t['us']:>10.0f} {t['main']:>6.0f}/{t['callback']:>4.0f}/{t['zenoh']:>5.0f} {b['us']:>12.0f} "
            f"{b['main']:>6.0f}/{b['callback']:>4.0f}/{b['zenoh']:>5.0f} {ratio(t['us'], b['us']):>6.2f}")


def _med_dict(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Element-wise median of nested dicts of numbers."""
    out: dict[str, Any] = {}
    for key, val in rows[0].items():
        if isinstance(val, dict):
            out[key] = _med_dict([r[key] for r in rows])
        else:
            out[key] = med([r[key] for r in rows])
    return out


def case_lockstep(a: argparse.Namespace, work: Path, report: dict) -> None:
    from sim import refsim
    from tether.node import load_mission

    path = catalog.resolve(a.mission)
    m = load_mission(path, a.lockstep_duration)
    ticks = m.steps + 1
    say(f"\n== 1. lockstep speed: {a.mission} ({m.n} agents, {m.dim}D, {m.rate:g} Hz), {a.lockstep_duration:g} s of "
        f"mission time per run, window {WINDOW}, one process per plant on both sides (--separate-plants: tether run "
        f"co-locates them by default in lockstep, case 1b), {a.repeats} repeats; speed = mission s / wall s")
    if not a.no_variants:
        say("   experiments on the bare baseline: 'co-located' = each plant computed inside its agent process (one")
        say("   Zenoh hop per tick on the critical path instead of three); '+batched' = co-located, and each agent")
        say("   sends the recorder one message per 4 ticks instead of two per tick, window 16")
    rows = []
    for i in range(a.repeats):
        settle()
        # the baseline's structure: one process per plant (tether run co-locates them by default in lockstep)
        rt = run_tether(path, m, "lockstep", a.lockstep_duration, work, extra=("--separate-plants", "--window", str(WINDOW)),
                        secure=a.secure)
        settle()
        rb = run_baseline(m, "lockstep", a.lockstep_duration, work, secure=a.secure)
        rc = rcb = None
        if not a.no_variants:
            settle()
            rc = run_baseline(m, "lockstep", a.lockstep_duration, work, variant={"colocate": True}, secure=a.secure)
            settle()
            rcb = run_baseline(m, "lockstep", a.lockstep_duration, work,
                               variant={"colocate": True, "batch": 4, "window": 16}, secure=a.secure)
        t0 = time.perf_counter()
        refsim.simulate(m, "discrete")
        ref = m.duration / (time.perf_counter() - t0)
        for res in (rt, rb, rc, rcb):
            if res is not None and not res.ok:
                say(f"   {res.kind} failed: {res.why}")

        def speed(res: Result | None) -> float:
            return res.speed if res is not None and res.ok else float("nan")

        row: dict[str, Any]  # a JSON record of mixed values, as _quiet and _med_dict take it
        row = {"tether": speed(rt), "baseline": speed(rb), "colocated": speed(rc), "batched": speed(rcb),
               "refsim": ref, "tether_cpu": _per_tick(rt, ticks), "baseline_cpu": _per_tick(rb, ticks),
               "colocated_cpu_us": _per_tick(rc, ticks)["total_us"] if rc is not None else float("nan"),
               "batched_cpu_us": _per_tick(rcb, ticks)["total_us"] if rcb is not None else float("nan"),
               "foreign_pct": [rt.foreign_pct, rb.foreign_pct],
               "startup_s": [rt.startup_s, rb.startup_s]}
        rows.append(row)
        noisy = " NOISY" if max(row["foreign_pct"]) >= NOISY else ""
        variants = "" if a.no_variants else (f"co-located {row['colocated']:5.2f} x  +batched "
                                             f"{row['batched']:5.2f} x  ")
        say(f"   run {i + 1}: tether {row['tether']:5.2f} x  baseline {row['baseline']:5.2f} x  {variants}"
            f"refsim {ref:5.0f} x | CPU per tick {row['tether_cpu']['total_us'] / 1e3:.2f} vs "
            f"{row['baseline_cpu']['total_us'] / 1e3:.2f} ms | other load {rt.foreign_pct:.0f} / {rb.foreign_pct:.0f} % "
            f"| start-up {rt.startup_s:.1f} / {rb.startup_s:.1f} s{noisy}")
    use = _quiet(rows)
    mm = _med_dict([{k: v for k, v in r.items() if k not in ("foreign_pct", "startup_s")} for r in use])
    say(f"   medians over {len(use)} of {len(rows)} runs (runs with other load >= {NOISY:g} % left out when a "
        "quiet one exists)")
    st, sb, sc, sr = mm["tether"], mm["baseline"], mm["colocated"], mm["refsim"]
    say(f"   median: tether {st:.2f} x real time ({1e3 * m.dt / st:.2f} ms per tick; target >= 20 x)")
    say(f"           bare baseline {sb:.2f} x ({1e3 * m.dt / sb:.2f} ms per tick): tether / baseline = {ratio(st, sb):.2f}")
    if not a.no_variants:
        say(f"           bare co-located {sc:.2f} x; bare co-located + batched + window 16 {mm['batched']:.2f} x")
    say(f"           reference simulator {sr:.0f} x: tether / refsim = {ratio(st, sr):.3f}")
    say(f"           CPU per tick, all processes: tether {mm['tether_cpu']['total_us'] / 1e3:.2f} ms, baseline "
        f"{mm['baseline_cpu']['total_us'] / 1e3:.2f} ms (ratio {ratio(mm['tether_cpu']['total_us'], mm['baseline_cpu']['total_us']):.2f})"
        + ("" if a.no_variants else f", co-located {mm['colocated_cpu_us'] / 1e3:.2f} ms, + batched "
                                    f"{mm['batched_cpu_us'] / 1e3:.2f} ms"))
    _role_table(mm["tether_cpu"], mm["baseline_cpu"], "CPU per tick by role [us], median process; thread kinds: asyncio main / "
                "callback threads / Zenoh runtime")
    report["lockstep"] = {"mission": a.mission, "n": m.n, "rate": m.rate, "duration": a.lockstep_duration,
                          "window": WINDOW, "runs": rows, "median": mm}


def colocate_structures(windows: list[str], mesh: bool = False
                        ) -> list[tuple[str, dict[str, Any], tuple[str, ...]]]:
    """Case ``colocate``: (name, bare baseline variant, ``tether run`` options) of each structure,
    the same on both sides: separate plant processes (window 8); plants co-located, the recorder's
    samples every tick (tether: one record per tick, the bare baseline two messages); then for
    each ``WINDOW:BATCH`` of ``windows``, co-located with records of BATCH ticks and that window.
    ``mesh``: each of those also as a peer mesh (``--network mesh``, which ``tether run`` picks by
    default for these runs up to ``deploy.options.MESH_MAX_AGENTS`` agents), beside the bare baseline
    as the same mesh."""
    out: list[tuple[str, dict[str, Any], tuple[str, ...]]] = [
        ("separate, w8", {}, ("--separate-plants", "--window", "8", "--network", "star")),
        ("co-located, w8", {"colocate": True}, ("--colocate-plants", "--record-batch", "1", "--network", "star")),
    ]
    for spec in windows:
        w, b = (int(x) for x in spec.split(":"))
        opts = ("--colocate-plants", "--record-batch", str(b), "--window", str(w))
        # the star named: a co-located run of up to 16 agents is a mesh by default (deploy.options.resolve)
        out.append((f"co+batch {b}, w{w}", {"colocate": True, "batch": b, "window": w}, (*opts, "--network", "star")))
        if mesh:
            out.append((f"co+b {b}, w{w}, mesh", {"colocate": True, "batch": b, "window": w, "mesh": True},
                        (*opts, "--network", "mesh")))
    return out


def case_network(a: argparse.Namespace, work: Path, report: dict) -> None:
    """Lockstep, plants co-located, the star against the peer mesh at each N of ``--network-sizes``
    (ring missions, ``--network-rate``), one after the other in each repeat: speed, start-up (the
    command's start to every process up) and the whole command's wall time; which one
    ``tether run`` picks by default (``deploy.options.MESH_MAX_AGENTS``)."""
    from deploy.options import MESH_MAX_AGENTS

    say(f"\n== 1c. lockstep star against mesh: ring missions, 3D, {a.network_rate:g} Hz, {a.network_duration:g} s of "
        f"mission time per run, {a.repeats} repeats, plants co-located (window 32, records of 16); speed = mission s / "
        f"wall s of the run; start = command start to every process up; total = the whole command")
    rows: dict[tuple[int, str], list[dict[str, float]]] = {}
    for i in range(a.repeats):
        for n in a.network_sizes:
            path, m = mission_file(work, n, a.network_rate, a.network_duration)
            for net in ("star", "mesh"):
                settle()
                t0 = time.monotonic()
                r = run_tether(path, m, "lockstep", a.network_duration, work, secure=a.secure,
                               extra=("--colocate-plants", "--network", net), timeout=600.0)
                total = time.monotonic() - t0
                row = {"speed": r.speed if r.ok else float("nan"), "start": r.startup_s, "total": total,
                       "foreign_pct": r.foreign_pct}
                rows.setdefault((n, net), []).append(row)
                say(f"   run {i + 1} N = {n:2d} {net:4}  {row['speed']:6.2f} x  start {row['start']:5.2f} s  total "
                    f"{total:6.2f} s  other {r.foreign_pct:.0f} %" + ("" if r.ok else f"  FAILED: {r.why}"))
    say(f"   medians: {'N':>3} {'star x':>7} {'mesh x':>7} {'mesh/star':>9} {'start star':>10} {'mesh':>6} "
        f"{'total star':>10} {'mesh':>6}  default")
    med_rows = {}
    for n in a.network_sizes:
        st, me = ({k: med([r[k] for r in rows[n, net]]) for k in ("speed", "start", "total")}
                  for net in ("star", "mesh"))
        med_rows[n] = {"star": st, "mesh": me}
        say(f"            {n:>3} {st['speed']:>7.2f} {me['speed']:>7.2f} {ratio(me['speed'], st['speed']):>9.2f} "
            f"{st['start']:>10.2f} {me['start']:>6.2f} {st['total']:>10.2f} {me['total']:>6.2f}  "
            f"{'mesh' if n <= MESH_MAX_AGENTS else 'star'}")
    report["network"] = {"rate": a.network_rate, "duration": a.network_duration, "median": med_rows,
                         "runs": {f"{n}-{net}": v for (n, net), v in rows.items()}}


def case_colocate(a: argparse.Namespace, work: Path, report: dict) -> None:
    """Lockstep, tether beside the bare baseline with the same structure (plants in separate
    processes or co-located in their agents, the recorder's samples per tick or batched, the grant
    window), one pair after the other in each repeat: speed, CPU per tick of all processes and of
    the median agent, and tether / bare of each, in the same run."""
    from tether.node import load_mission

    path = catalog.resolve(a.mission)
    m = load_mission(path, a.lockstep_duration)
    ticks = m.steps + 1
    structs = colocate_structures(a.colocate_windows, a.colocate_mesh)
    say(f"\n== 1b. lockstep by structure: {a.mission} ({m.n} agents, {m.rate:g} Hz), {a.lockstep_duration:g} s of mission "
        f"time per run, {a.repeats} repeats; tether run with the structure's options beside the bare baseline with the "
        "same structure; speed = mission s / wall s; CPU per tick from /proc (all processes / median agent)")
    rows: dict[str, list[dict[str, Any]]] = {name: [] for name, _, _ in structs}
    for i in range(a.repeats):
        for name, variant, opts in structs:
            settle()
            rt = run_tether(path, m, "lockstep", a.lockstep_duration, work, extra=opts, secure=a.secure)
            settle()
            rb = run_baseline(m, "lockstep", a.lockstep_duration, work, variant=variant, secure=a.secure)
            bad = [f"{r.kind} failed: {r.why}" for r in (rt, rb) if not r.ok]
            ct, cb = _per_tick(rt, ticks), _per_tick(rb, ticks)
            row = {"tether": rt.speed if rt.ok else float("nan"),
                   "baseline": rb.speed if rb.ok else float("nan"),
                   "tether_us": ct["total_us"], "baseline_us": cb["total_us"], "tether_agent_us": ct["agent"]["us"],
                   "baseline_agent_us": cb["agent"]["us"], "tether_cpu": ct, "baseline_cpu": cb,
                   "foreign_pct": [rt.foreign_pct, rb.foreign_pct],
                   "load": os.getloadavg()[0]}
            rows[name].append(row)
            noisy = " NOISY" if max(row["foreign_pct"]) >= NOISY else ""
            say(f"   run {i + 1} {name:17} tether {row['tether']:5.2f} x  bare {row['baseline']:5.2f} x  "
                f"({ratio(row['tether'], row['baseline']):.2f}) | CPU/tick {row['tether_us'] / 1e3:.2f} vs "
                f"{row['baseline_us'] / 1e3:.2f} ms ({ratio(row['tether_us'], row['baseline_us']):.2f}) | agent "
                f"{row['tether_agent_us']:.0f} vs {row['baseline_agent_us']:.0f} us | other {rt.foreign_pct:.0f} / "
                f"{row['foreign_pct'][1]:.0f} % | load {row['load']:.1f}{noisy}" + ("".join(f"\n      {x}" for x in bad)))
    say(f"   medians over the quiet runs (other load < {NOISY:g} %, or all runs when none is quiet):")
    say(f"   {'structure':17} {'tether x':>9} {'bare x':>7} {'ratio':>6} {'CPU/tick ms':>12} {'bare':>6} {'ratio':>6} "
        f"{'agent us':>9} {'bare':>6} {'ratio':>6}")
    med_rows = {}
    for name, _, _ in structs:
        use = _quiet(rows[name])
        mm = {k: med([r[k] for r in use]) for k in ("tether", "baseline", "tether_us", "baseline_us",
                                                      "tether_agent_us", "baseline_agent_us", "load")}
        med_rows[name] = mm
        say(f"   {name:17} {mm['tether']:>9.2f} {mm['baseline']:>7.2f} {ratio(mm['tether'], mm['baseline']):>6.2f} "
            f"{mm['tether_us'] / 1e3:>12.2f} {mm['baseline_us'] / 1e3:>6.2f} {ratio(mm['tether_us'], mm['baseline_us']):>6.2f} "
            f"{mm['tether_agent_us']:>9.0f} {mm['baseline_agent_us']:>6.0f} "
            f"{ratio(mm['tether_agent_us'], mm['baseline_agent_us']):>6.2f}")
    best = max(med_rows, key=lambda n: med_rows[n]["tether"])
    ceiling = max(med_rows, key=lambda n: med_rows[n]["baseline"])
    say(f"   fastest tether structure: {best} ({med_rows[best]['tether']:.2f} x real time; target >= 20 x; its bare "
        f"ceiling {med_rows[best]['baseline']:.2f} x); the fastest bare structure: {ceiling} "
        f"({med_rows[ceiling]['baseline']:.2f} x); separate plants: {med_rows[structs[0][0]]['tether']:.2f} x")
    mid = rows[best][len(rows[best]) // 2]  # the role table: the fastest structure
    _role_table(mid["tether_cpu"], mid["baseline_cpu"],
                f"{best}, CPU per tick by role [us] (one run), thread kinds: asyncio main / callback / Zenoh runtime")
    report["colocate"] = {"mission": a.mission, "duration": a.lockstep_duration, "runs": rows, "median": med_rows}


def _rt_row(rt: Result, rb: Result) -> dict[str, Any]:
    """What a real-time pair (tether, baseline) gives: late ticks, CPU, memory, ages, losses."""
    ticks = rt.rate * rt.mission_s + 1 if rt.mission_s == rt.mission_s else float("nan")

    def mem(res: Result) -> dict[str, float]:
        return {kind: med(res.mem_mib("agent", kind)) for kind in ("rss", "pss", "uss")}

    return {"n": rt.n, "rate": rt.rate, "tether_ok": rt.ok, "tether_status": rt.status, "tether_why": rt.why.strip()[-300:],
            "baseline_ok": rb.ok, "tether_late": rt.late, "tether_late_max": rt.late_max, "baseline_late": rb.late,
            "tether_total_cpu": rt.total_cpu_pct(), "baseline_total_cpu": rb.total_cpu_pct(),
            "tether_cpu_by_role": {ro: med(rt.cpu_pct(ro)) for ro in ROLES},
            "baseline_cpu_by_role": {ro: med(rb.cpu_pct(ro)) for ro in ROLES},
            "tether_per_tick": _per_tick(rt, ticks) if rt.ok else None,
            "baseline_per_tick": _per_tick(rb, ticks) if rb.ok else None,
            "tether_agent_mem_mib": mem(rt), "baseline_agent_mem_mib": mem(rb),
            "link_age_ms": [1e3 * pct(rt.link_age, q) if rt.link_age is not None else float("nan") for q in (50, 99)],
            "stale_ticks": 100 * float(np.mean(rt.link_age > 1e-9)) if rt.link_age is not None and rt.link_age.size
            else float("nan"),
            "meas_age_ms": [1e3 * pct(rt.meas_age, q) if rt.meas_age is not None else float("nan") for q in (50, 99)],
            "tether_recorded": rt.complete, "baseline_recorded": rb.complete,
            "foreign_pct": [rt.foreign_pct, rb.foreign_pct],
            "startup_s": [rt.startup_s, rb.startup_s]}


def _recorded(recorded: str) -> tuple[int, int] | None:
    """``(got, sent)`` from a run's ``"24781/24783"`` (samples recorded of those sent), None if unreadable."""
    try:
        got, want = (int(x) for x in recorded.split("/"))
    except ValueError:
        return None
    return got, want


def _lost(recorded: str) -> str:
    """``"2 of 24783"`` from a run's ``"24781/24783"``."""
    pair = _recorded(recorded)
    return "?" if pair is None else f"{pair[1] - pair[0]} of {pair[1]}"


def _frac(recorded: str) -> float:
    """The share recorded [%] of a run's ``"24781/24783"`` (NaN if unreadable or nothing was sent)."""
    pair = _recorded(recorded)
    return 100 * pair[0] / pair[1] if pair is not None and pair[1] else float("nan")


def case_scale(a: argparse.Namespace, work: Path, report: dict, pairs: list) -> None:
    say(f"\n== 2. real-time scale: ring missions, 3D, {a.scale_rate:g} Hz, {a.rt_duration:g} s per run, "
        f"{a.scale_repeats} run(s) per N; on time = under 1 % of agent ticks late (started > 1 period late, median")
    say("   over the quiet runs) and every run went to its end (exit 0, or 5: samples lost on the way); holds = on time")
    say("   and every run ended clean (exit 0). CPU = sum over every process (launcher/router included)")
    say("   over the mission window [% of one core]; recorded = samples the recorder got of those sent;")
    say("   other = other users' CPU during the run (tether / baseline)")
    if a.scale_shared:
        say("   tether runs with --shared-plants: one world process steps every vehicle (the baseline keeps one "
            "process per plant)")
    say(f"   {'N':>3} {'procs':>5} {'late %':>7} {'worst':>6} {'bl late':>7} {'CPU':>6} {'bl CPU':>6} {'ratio':>5} "
        f"{'recorded %':>12} {'link age ms':>12} {'other %':>8}")
    rows = []
    largest = largest_on_time = None
    for n in a.sizes:
        path, m = mission_file(work, n, a.scale_rate, a.rt_duration)
        runs = []
        for _ in range(a.scale_repeats):
            settle()
            rt = run_tether(path, m, "realtime", a.rt_duration, work,
                            extra=("--shared-plants",) if a.scale_shared else (), secure=a.secure)
            settle()
            rb = run_baseline(m, "realtime", a.rt_duration, work, wake=a.baseline_wake, secure=a.secure)
            pairs.append((rt, rb))
            row = _rt_row(rt, rb)
            runs.append(row)
            noisy = " NOISY" if max(row["foreign_pct"]) >= NOISY else ""
            say(f"   {n:>3} {len(rt.cpu_pct()):>5} {100 * rt.late:>7.2f} {100 * rt.late_max:>6.2f} {100 * rb.late:>7.2f} "
                f"{row['tether_total_cpu']:>6.0f} {row['baseline_total_cpu']:>6.0f} "
                f"{ratio(row['tether_total_cpu'], row['baseline_total_cpu']):>5.2f} "
                f"{_frac(rt.complete):>5.1f}/{_frac(rb.complete):<6.1f} "
                f"{row['link_age_ms'][0]:>5.1f}/{row['link_age_ms'][1]:<6.1f} "
                f"{rt.foreign_pct:>3.0f}/{rb.foreign_pct:<4.0f}{noisy}"
                + ("" if rt.ok else f"  FAILED ({rt.why.strip()[-160:]})"))
        use = _quiet(runs)
        late = med([r["tether_late"] for r in use])
        on_time = all(r["tether_status"] in (0, 5) for r in runs) and late == late and late < 0.01
        holds = on_time and all(r["tether_ok"] for r in runs)
        lost = [_lost(r["tether_recorded"]) for r in runs if r["tether_status"] == 5]
        rows.append({"n": n, "runs": runs, "late": late, "holds": holds, "on_time": on_time,
                     "tether_total_cpu": med([r["tether_total_cpu"] for r in use]),
                     "baseline_total_cpu": med([r["baseline_total_cpu"] for r in use])})
        say(f"   {n:>3} agents: median late {100 * late:.2f} %, CPU {rows[-1]['tether_total_cpu']:.0f} % vs "
            f"{rows[-1]['baseline_total_cpu']:.0f} % (ratio {ratio(rows[-1]['tether_total_cpu'], rows[-1]['baseline_total_cpu']):.2f})"
            f" -> {'holds' if holds else 'on time' if on_time else 'does NOT hold'} {a.scale_rate:g} Hz"
            + (f" (samples lost on the way in {len(lost)} of {len(runs)} runs: {', '.join(lost)})" if lost else ""))
        if holds:
            largest = n
        if on_time:
            largest_on_time = n
        elif not a.scale_all:
            break
    say(f"   largest N holding {a.scale_rate:g} Hz here: {largest}; on time (< 1 % late, every run to its end): "
        f"{largest_on_time}")
    report["scale"] = {"rate": a.scale_rate, "duration": a.rt_duration, "rows": rows, "largest": largest,
                       "largest_on_time": largest_on_time}


def case_latency(a: argparse.Namespace, work: Path, report: dict, pairs: list) -> None:
    n, rate = a.latency_n, a.latency_rate
    path, m = mission_file(work, n, rate, a.latency_duration)
    say(f"\n== 3. latency: ring of {n}, {rate:g} Hz, {a.latency_duration:g} s; a probe subscribes to every plant's and "
        f"agent's state ({a.repeats} repeats); microseconds, p50 / p99, tether vs baseline")
    say("   plant: plant tick instant -> probe callback (plant timer + one hop through the router)")
    say("   relay: probe arrival of agent i's relay of plant i's sample k - arrival of that sample itself (one more hop:")
    say("          router -> agent callback -> hand-off -> decode -> relay put -> router)")
    rows = []
    for i in range(a.repeats):
        settle()
        # --insecure: the probe is a plain Zenoh client on the launcher's endpoint (TLS with client
        # certificates, the default, refuses it), and the bare baseline has no TLS either
        rt = run_tether(path, m, "realtime", a.latency_duration, work, probe=True, secure=False)
        settle()
        rb = run_baseline(m, "realtime", a.latency_duration, work, probe=True, wake=a.baseline_wake, secure=False)
        pairs.append((rt, rb))
        row = _rt_row(rt, rb)
        row["tether_probe"], row["baseline_probe"] = probe_stats(rt.probe, rate), probe_stats(rb.probe, rate)
        tp_, bp = row["tether_probe"], row["baseline_probe"]
        if "error" in tp_ or "error" in bp:
            say(f"   run {i + 1}: probe failed: {tp_.get('error')} {bp.get('error')}")
            continue
        rows.append(row)
        noisy = " NOISY" if max(row["foreign_pct"]) >= NOISY else ""
        say(f"   run {i + 1}: plant {tp_['plant_tick'][0]:.0f}/{tp_['plant_tick'][1]:.0f} vs {bp['plant_tick'][0]:.0f}/"
            f"{bp['plant_tick'][1]:.0f}; relay {tp_['relay'][0]:.0f}/{tp_['relay'][1]:.0f} vs {bp['relay'][0]:.0f}/"
            f"{bp['relay'][1]:.0f}; bare put->callback {bp['put_cb'][0]:.0f}/{bp['put_cb'][1]:.0f}; late "
            f"{100 * rt.late:.2f} %; recorded {_frac(rt.complete):.1f}/{_frac(rb.complete):.1f} %; link age "
            f"{row['link_age_ms'][0]:.0f}/{row['link_age_ms'][1]:.0f} ms; other load "
            f"{rt.foreign_pct:.0f}/{rb.foreign_pct:.0f} %{noisy}")
    if not rows:
        return
    use = _quiet(rows)
    mm: dict[str, Any] = {}
    for who in ("tether", "baseline"):
        for name in ("plant_tick", "agent_tick", "relay", "put_cb"):
            mm[f"{who}_{name}"] = [med([r[f"{who}_probe"][name][j] for r in use]) for j in (0, 1)]
        mm[f"{who}_after_phase"] = {ph: med([r[f"{who}_probe"]["after_phase"][ph] for r in use])
                                    for ph in use[0][f"{who}_probe"]["after_phase"]}
    age = [med([r["link_age_ms"][j] for r in use]) for j in (0, 1)]
    meas = [med([r["meas_age_ms"][j] for r in use]) for j in (0, 1)]
    stale = med([r["stale_ticks"] for r in use])
    say(f"   medians over {len(use)} of {len(rows)} runs (noisy runs left out when a quiet one exists):")
    say(f"     plant tick -> callback   tether {mm['tether_plant_tick'][0]:.0f} / {mm['tether_plant_tick'][1]:.0f}, "
        f"baseline {mm['baseline_plant_tick'][0]:.0f} / {mm['baseline_plant_tick'][1]:.0f}  "
        f"(p99 ratio {ratio(mm['tether_plant_tick'][1], mm['baseline_plant_tick'][1]):.2f})")
    say(f"     relay hop via an agent   tether {mm['tether_relay'][0]:.0f} / {mm['tether_relay'][1]:.0f}, "
        f"baseline {mm['baseline_relay'][0]:.0f} / {mm['baseline_relay'][1]:.0f}  "
        f"(p99 ratio {ratio(mm['tether_relay'][1], mm['baseline_relay'][1]):.2f}; target p99 < 2000 and <= 1.5 x)")
    say(f"     bare put -> callback     {mm['baseline_put_cb'][0]:.0f} / {mm['baseline_put_cb'][1]:.0f}")
    say("     relayed samples arriving after phase x period (a neighbour ticking at that phase misses them), "
        "tether / baseline: " + ", ".join(f"{ph}: {100 * mm['tether_after_phase'][ph]:.2f} / "
                                          f"{100 * mm['baseline_after_phase'][ph]:.2f} %" for ph in mm["tether_after_phase"]))
    say(f"     neighbour data age at use (links.age) {age[0]:.1f} / {age[1]:.1f} ms; own measurement age "
        f"(runtime.meas_age) {meas[0]:.1f} / {meas[1]:.1f} ms; agent ticks using older-than-current samples "
        f"{stale:.2f} %; period {1e3 / rate:.1f} ms, agents tick at phase {AGENT_PHASE:g}")
    report["latency"] = {"n": n, "rate": rate, "duration": a.latency_duration, "runs": rows, "median": mm,
                         "link_age_ms": age, "meas_age_ms": meas, "stale_ticks_pct": stale,
                         "agent_phase": AGENT_PHASE, "quiet_runs": len(use)}


KINDS = ("main", "callback", "zenoh")
"""Thread kinds (:func:`thread_cpu`), in the order the tables print them."""


def case_cpu(a: argparse.Namespace, work: Path, report: dict, pairs: list) -> None:
    if not pairs:
        path, m = mission_file(work, 8, a.scale_rate, a.rt_duration)
        for _ in range(a.cpu_repeats):  # pairs one right after the other; the medians are over them
            settle()
            rt = run_tether(path, m, "realtime", a.rt_duration, work, secure=a.secure)
            settle()
            pairs.append((rt, run_baseline(m, "realtime", a.rt_duration, work, wake=a.baseline_wake,
                                           secure=a.secure)))
    say("\n== 4. per agent process, real time: CPU [% of one core] and memory [MiB] (median process; tether / "
        "baseline = ratio)")
    say("   RSS counts shared library pages in full in every process; PSS divides them among their users;")
    say("   USS is what the process alone holds")
    say(f"   {'N':>3} {'Hz':>4} {'agent CPU':>20} {'agent RSS':>20} {'agent PSS':>20} {'agent USS':>20} "
        f"{'plant CPU':>17} {'recorder CPU':>17}")
    rows = []
    for rt, rb in pairs:
        # a run that went to its end with a few samples missing from the file (exit 5) held its rate
        if not (rt.ran_to_end and rb.ok and rt.late < 0.01):
            say(f"   ({rt.n} agents at {rt.rate:g} Hz left out: tether did not hold the rate, so its CPU is capped)")
            continue
        if max(rt.foreign_pct, rb.foreign_pct) >= NOISY:
            say(f"   ({rt.n} agents at {rt.rate:g} Hz left out: noisy run, other load {rt.foreign_pct:.0f} / "
                f"{rb.foreign_pct:.0f} %)")
            continue
        row: dict[str, Any] = {"n": rt.n, "rate": rt.rate}
        cells = []
        for ro, what, width in (("agent", "cpu", 20), ("agent", "rss", 20), ("agent", "pss", 20), ("agent", "uss", 20),
                                ("plant", "cpu", 17), ("recorder", "cpu", 17)):
            if what == "cpu":
                x, y = med(rt.cpu_pct(ro)), med(rb.cpu_pct(ro))
            else:
                x, y = med(rt.mem_mib(ro, what)), med(rb.mem_mib(ro, what))
            row[f"{ro}_{what}"] = [x, y, ratio(x, y)]
            cells.append(f"{x:.1f}/{y:.1f}={ratio(x, y):.2f}".rjust(width))
        rows.append(row)
        say(f"   {rt.n:>3} {rt.rate:>4g} " + " ".join(cells))
        # where each role's CPU goes: its asyncio thread, zenoh-python's callback threads, Zenoh's own
        split = []
        for ro in ("agent", "plant", "recorder"):
            x, y = rt.thread_pct(ro), rb.thread_pct(ro)
            row[f"{ro}_threads"] = {"tether": x, "baseline": y}
            split.append(f"{ro} " + "/".join(f"{x[k]:.1f}" for k in KINDS) + " vs "
                         + "/".join(f"{y[k]:.1f}" for k in KINDS))
        say("        by thread (main / callback / Zenoh) [% of a core], tether vs bare: " + "; ".join(split))
    if rows:
        summary = {k: med([r[k][2] for r in rows]) for k in rows[0] if k not in ("n", "rate") and not k.endswith("_threads")}
        say(f"   median ratios: agent CPU {summary['agent_cpu']:.3f} (target <= 1.2), agent RSS {summary['agent_rss']:.3f} "
            f"(target <= 1.1), PSS {summary['agent_pss']:.2f}, USS {summary['agent_uss']:.2f}; plant CPU "
            f"{summary['plant_cpu']:.2f}, recorder CPU {summary['recorder_cpu']:.2f}")
        report["cpu"] = {"rows": rows, "median_ratios": summary}


def case_python(a: argparse.Namespace, work: Path, report: dict) -> None:
    """The Python work of one tick per role, in this process, hot (timeit): what the runtime must
    spend whatever the transport, against the CPU per tick its processes take (cases 1 and 4)."""
    import asyncio
    import math
    import timeit

    from agent.law import AgentLaw
    from leader import profile
    from plant import double_integrator
    from plant.disturbance import DisturbanceBank

    _, m = mission_file(work, a.latency_n, a.latency_rate, 1.0)
    d, h = m.dim, m.dt
    width = max(sum(1 for e in m.edges if e.dst == ag.id) for ag in m.agents)
    rx = wire.Receiver(d)
    enc = {name: wire.encode(example_message(cls, m, width)) for name, cls in
           (("state", wire.State), ("plant", wire.PlantState), ("cmd", wire.Command), ("tele", wire.Telemetry))}
    vec = [0.1] * d

    def us(f: Any, n: int = 20000) -> float:
        return 1e6 * timeit.timeit(f, number=n) / n

    rows: dict[str, float] = {}
    rows["msgpack decode, PlantState"] = us(lambda: wire.decode(enc["plant"]))
    rows["Receiver.accept, PlantState"] = us(lambda: rx.accept(enc["plant"], wire.PlantState, m.leader.id))
    rows["Receiver.accept, Telemetry"] = us(lambda: rx.accept(enc["tele"], wire.Telemetry, m.leader.id))
    rows["construct + encode, State"] = us(lambda: wire.encode(wire.State(sender=1, seq=1, k=1, t=0.01, p=vec,
                                                                          vel=vec, a=vec)))
    dist = DisturbanceBank.from_mission(m, [m.agent_ids[0]])
    p0 = np.zeros(d)

    def plant_tick() -> bytes:
        u = np.array(vec)
        dv, dp = dist.increments(5)
        p, v, acc = double_integrator.step(p0, p0, u, dv[0], dp[0], h)
        dd = dist.value(5)[0]
        return wire.encode(wire.PlantState(sender=1, seq=5, k=5, t=0.05, p=p.tolist(), vel=v.tolist(),
                                           a=acc.tolist(), d=dd.tolist()))

    rows["plant tick: integrate + disturbance + encode"] = us(plant_tick)
    ref = profile.build(m.leader, d)
    rows["leader tick: profile + encode"] = us(lambda: wire.encode(wire.State(
        sender=1, seq=1, k=1, t=0.01, **dict(zip(("p", "vel", "a"), (x.tolist() for x in ref(0.05)))))))
    law = AgentLaw.from_mission(m, m.agent_ids[0])
    nb = np.zeros((len(law.neighbours), d))
    kp, kv = (np.array(x) for x in law.initial())
    # AgentLaw.step takes numpy arrays as well as lists (its docstring), but is annotated for lists
    # (tether.vec.Vec): the arrays this figure times, cast outside the timed call (the same objects)
    p0_s, kp_s, kv_s = cast(Sequence[float], p0), cast(Sequence[float], kp), cast(Sequence[float], kv)
    nb_s = cast(Sequence[Sequence[float]], nb)
    rows["AgentLaw.step (numpy, d = 3)"] = us(lambda: law.step(p0_s, p0_s, nb_s, nb_s, nb_s, kp_s, kv_s))
    rows["isfinite over a 3-vector: generator / map"] = us(lambda: all(math.isfinite(x) for x in vec))
    rows["  ... all(map(math.isfinite, v))"] = us(lambda: all(map(math.isfinite, vec)))

    with_t, without_t, bare = asyncio.run(_wakeups())
    rows["Wakeup.notify + wait(timeout) on the loop"] = with_t
    rows["Wakeup.notify + wait() on the loop"] = without_t
    rows["bare call_soon + Event.wait"] = bare
    say(f"\n== Python work per tick, in one process, hot caches (timeit; {m.n} agents, {d}D); microseconds")
    for name, val in rows.items():
        say(f"   {name:48} {val:7.2f}")
    report["python_us"] = rows


async def _wakeups(n: int = 20000) -> tuple[float, float, float]:
    """CPU [us] of one hand-off on the running loop: :class:`tether.handoff.Wakeup` with a timeout,
    without one, and a bare ``call_soon`` + ``asyncio.Event`` (``n`` of each, in this thread)."""
    import asyncio

    w, loop, ev = handoff.Wakeup(), asyncio.get_running_loop(), asyncio.Event()
    t0 = time.thread_time()
    for _ in range(n):
        w.notify()
        await w.wait(30.0)
    t1 = time.thread_time()
    for _ in range(n):
        w.notify()
        await w.wait()
    t2 = time.thread_time()
    for _ in range(n):
        loop.call_soon(ev.set)
        await ev.wait()
        ev.clear()
    t3 = time.thread_time()
    return 1e6 * (t1 - t0) / n, 1e6 * (t2 - t1) / n, 1e6 * (t3 - t2) / n


def profile_run(mission: str, clock: ClockKind, duration: float, who: str, work: Path, top: int = 25,
                colocate: str | None = None) -> None:
    """Run ``tether run`` (launcher in this process) with one child under cProfile and print where its
    time goes. ``who`` is ``role:id`` (``agent:1``, ``recorder:0``, ...). The child is started by the
    launcher exactly as usual but through ``bench/runtime.py _cprofile FILE`` instead of ``-m
    cli.main``: ``cProfile`` with ``time.thread_time`` as its timer, so the figures are CPU time of
    the asyncio thread (time asleep in epoll counts as zero, Zenoh's and the callbacks' threads are
    not in it: see the per-thread CPU of the cases for those)."""
    import asyncio
    import cProfile  # noqa: F401  (the child runs it)
    import pstats
    from unittest import mock

    from deploy import children, local, options
    from tether.node import load_mission

    role, nid = who.split(":")
    path = catalog.resolve(mission)
    out = work / f"profile-{role}-{nid}-{clock}"
    prof = out / f"{role}-{nid}.prof"
    out.mkdir(parents=True, exist_ok=True)
    real_popen = subprocess.Popen

    def popen(cmd: list[str], *args: Any, **kwargs: Any) -> subprocess.Popen[Any]:
        if "cli" in cmd and cmd[cmd.index("cli") + 1] == role and \
                (role in ("leader", "recorder") or cmd[cmd.index("--id") + 1] == nid):
            i = cmd.index("-m")
            cmd = [*cmd[:i], __file__, "_cprofile", str(prof), *cmd[i + 2:]]
        return real_popen(cmd, *args, **kwargs)

    load_mission(path, duration)
    window, batch = (int(x) for x in colocate.split(":")) if colocate else (options.WINDOW, None)
    opts = options.LaunchOptions(out=out, clock=clock, duration=duration, progress=False, window=window,
                                 colocate_plants=colocate is not None, record_batch=batch)
    with mock.patch.object(children.subprocess, "Popen", popen):  # restored when the run ends, however it ends
        status = asyncio.run(local.run(path, opts))
    say(f"tether run {mission} --clock {clock} --duration {duration:g}: exit {status}; profile of {role}/{nid}: {prof}")
    if prof.exists():
        st = pstats.Stats(str(prof))
        st.sort_stats("tottime").print_stats(top)
        st.sort_stats("cumulative").print_stats(top)


def cprofile_child(out: str, args: list[str]) -> int:
    """``python bench/runtime.py _cprofile OUT <cli.main args>``: run the CLI under cProfile timed by
    the main thread's CPU clock; stats are written to OUT when it returns (SIGTERM ends it normally)."""
    import cProfile
    import signal

    from cli import main as cli

    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    prof = cProfile.Profile(time.thread_time)
    try:
        return prof.runcall(cli.main, args)
    finally:
        prof.dump_stats(out)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+",
                    choices=["lockstep", "colocate", "network", "scale", "latency", "cpu", "python"],
                    default=["lockstep", "scale", "latency", "cpu", "python"])
    ap.add_argument("--repeats", type=int, default=3, help="runs per figure in cases 1 and 3 (medians)")
    ap.add_argument("--mission", default="section4", help="case 1's mission (N = 4, 100 Hz)")
    ap.add_argument("--lockstep-duration", type=float, default=10.0, help="case 1: mission seconds per run")
    ap.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 16, 32], help="case 2: N, stepped until one fails")
    ap.add_argument("--scale-rate", type=float, default=50.0)
    ap.add_argument("--scale-repeats", type=int, default=1, help="case 2: runs per N (median late share)")
    ap.add_argument("--scale-all", action="store_true", help="case 2: run every N of --sizes, also past one that fails")
    ap.add_argument("--scale-shared", action="store_true",
                    help="case 2: tether runs with --shared-plants (one world process for every vehicle)")
    ap.add_argument("--rt-duration", type=float, default=15.0, help="case 2 (and 4): mission seconds per run")
    ap.add_argument("--cpu-repeats", type=int, default=1,
                    help="case 4 on its own: N = 8 pairs run one after the other (median ratios over them)")
    ap.add_argument("--latency-n", type=int, default=8)
    ap.add_argument("--latency-rate", type=float, default=100.0)
    ap.add_argument("--latency-duration", type=float, default=10.0)
    ap.add_argument("--no-variants", action="store_true", help="case 1: skip the co-located baseline experiment")
    ap.add_argument("--colocate-windows", nargs="*", default=["16:4", "16:8", "32:16"], metavar="WINDOW:BATCH",
                    help="case colocate: co-located structures with records of BATCH ticks and this grant window")
    ap.add_argument("--colocate-mesh", action="store_true",
                    help="case colocate: each co-located structure also as a peer mesh (tether run --network mesh, "
                         "the default up to 16 agents), beside the bare baseline as the same mesh")
    ap.add_argument("--network-sizes", type=int, nargs="+", default=[4, 8, 16, 24, 32],
                    help="case network: N of the ring missions flown as a star and as a mesh")
    ap.add_argument("--network-rate", type=float, default=100.0, help="case network: the missions' rate [Hz]")
    ap.add_argument("--network-duration", type=float, default=10.0, help="case network: mission seconds per run")
    ap.add_argument("--insecure", action="store_true",
                    help="tether run --insecure, and the baseline on plain TCP too (default: both authenticated, "
                         "mTLS with the run's access rules; the latency case is plain either way: its probe is)")
    ap.add_argument("--bare-loop", choices=["tether", "uvloop", "asyncio"], default="tether",
                    help="the bare baseline's event loop (default: the one tether's processes run on, "
                         "tether/evloop.py: uvloop where installed, TETHER_LOOP to choose)")
    ap.add_argument("--baseline-wake", action="store_true",
                    help="real-time baseline wakes its loop on every sample, as tether's nodes do")
    ap.add_argument("--quiet-below", type=float, default=0.5,
                    help="before each run, wait until the machine uses fewer cores than this (other users)")
    ap.add_argument("--quiet-timeout", type=float, default=60.0, help="... but no longer than this [s]")
    ap.add_argument("--work", type=Path, default=None, help="keep run directories here (default: a temp dir)")
    ap.add_argument("--json", type=Path, default=None, help="write every figure here")
    ap.add_argument("--profile", metavar="ROLE:ID", default=None,
                    help="instead of the cases: one tether run with this process under cProfile (e.g. agent:1)")
    ap.add_argument("--profile-clock", choices=["lockstep", "realtime"], default="lockstep")
    ap.add_argument("--profile-duration", type=float, default=10.0)
    ap.add_argument("--profile-colocate", metavar="WINDOW:BATCH", default=None,
                    help="--profile a lockstep run with --colocate-plants, this window and records of BATCH ticks")
    return ap


def main(argv: list[str]) -> None:
    if argv and argv[0] == "_cprofile":
        sys.exit(cprofile_child(argv[1], argv[2:]))
    a = _parser().parse_args(argv)
    a.secure = not a.insecure
    tether_loop = evloop.choose()
    LOOP["bare"] = tether_loop if a.bare_loop == "tether" else a.bare_loop
    compiled = compile_tree()
    if a.profile:
        work = a.work or Path(tempfile.mkdtemp(prefix="tether-profile-"))
        return profile_run(a.mission, a.profile_clock, a.profile_duration, a.profile, work,
                           colocate=a.profile_colocate)
    QUIET.update(limit=a.quiet_below, timeout=a.quiet_timeout)
    report: dict[str, Any] = {"machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0],
                                          "load_at_start": os.getloadavg()}}
    say(f"bench/runtime.py: {os.cpu_count()} CPUs, Python {sys.version.split()[0]}, load average at start "
        + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    say(f"   transport: {'mTLS, access rules' if a.secure else 'plain TCP (--insecure)'} for tether and the "
        f"baseline alike (the latency case: plain); bytecode of this tree compiled first ({compiled} files "
        "were stale), as an installed package has it")
    say(f"   event loop: tether {tether_loop}, the bare baseline {LOOP['bare']}")
    pairs: list = []
    with tempfile.TemporaryDirectory(prefix="tether-bench-") as tmp:
        work = a.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        t0 = time.monotonic()
        if "lockstep" in a.cases:
            case_lockstep(a, work, report)
        if "colocate" in a.cases:
            case_colocate(a, work, report)
        if "network" in a.cases:
            case_network(a, work, report)
        if "scale" in a.cases:
            case_scale(a, work, report, pairs)
        if "latency" in a.cases:
            case_latency(a, work, report, pairs)
        if "cpu" in a.cases:
            case_cpu(a, work, report, pairs)
        if "python" in a.cases:
            case_python(a, work, report)
        say(f"\ndone in {time.monotonic() - t0:.0f} s; load average at end " + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    if a.json is not None:
        report["machine"]["load_at_end"] = os.getloadavg()
        a.json.write_text(jsonout.dumps(report, indent=1, default=float))


if __name__ == "__main__":
    main(sys.argv[1:])
