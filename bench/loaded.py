"""A busy host: Section 4 in real time beside CPU-bound processes, at each CPU policy asked for.

    python bench/loaded.py                                  # 2 busy loops; no option, then --rt-priority 10; 3 pairs
    python bench/loaded.py --hogs 3 --reps 5 --priorities none 0 10
    python bench/loaded.py --repo ../other-checkout          # run another checkout's tether (its cwd first on the path)
    python bench/loaded.py --json loaded.json                # also keep every figure of every run

Each run: ``--hogs`` busy loops (``python -c 'while ...: pass'``, the default policy, each ending by
itself) start first; then ``tether run section4 --clock realtime --duration D --quiet --listen
tls/127.0.0.1:P`` (authenticated, as by default), with ``--rt-priority X`` for a priority X, or no
option for ``none`` (the launcher's own default). The bench attaches as the operator through the
run's operator gateway (``DIR/tls/control-0.json5``, as ``tether land`` does) with a tap that stamps
every agent's telemetry and every plant's state on arrival (``bench/faults.py`` :class:`Tap`). At
mission time ``--order-at`` the operator's order (``land`` in even repetitions, ``estop`` in odd
ones) is published from the tap's session (the message and copies of
:func:`deploy.operator.publish`), or, with ``--cli``, sent by the real command ``tether land|estop
--ns section4 --zenoh-config DIR/tls/control-0.json5``. Configurations alternate run by run (A, B,
A, B, ...), so that each pair shares the machine's state.

Figures per run, and their medians over the repetitions:

* ``load``: the 1-minute load average (``os.getloadavg``) as the run started.
* ``late``: the share of the agents' ticks that started more than a period late (the run file's
  ``late``, all agents).
* ``events``: every mode change of an agent's supervisor (``a2 F>H``) or a plant's watchdog
  (``p2 F>H``) before the order, with its reason: each one is a failsafe for nothing (nothing was
  attacked or broken).
* ``sep`` [m]: the smallest distance between two vehicles, from the plants' own positions, over the
  whole run (the start and the landing included); ``sep_fs``: the same from the first failsafe on.
* ``err`` [m]: the largest true formation error ``||p_i - h_i - p_L(t)||`` (plants' positions,
  offsets, the leader's analytic profile, never its recorded samples) over the second half of the
  flight before the order; ``err0`` the same over the first 10 s.
* ``land``/``estop`` *reached* [s]: from the order's first copy (``--cli``: the command's start, its
  start-up included) to the tick at which the last of the four plants' watchdogs took the ordered
  mode (the run file's plant events, mission time: tick-quantised); *seen*: to the tap's arrival of
  that plant's first state in the mode (the state's trip back through the gateway to an operator at
  the default policy included); ``nan`` if one never did (``reached`` says how many were seen).
* ``gateway``: the operator gateway's CPU policy as its log says, and ``exit`` the launcher's.

Bounded: the launcher is killed ``--duration`` + 120 s after it starts, the busy loops end by
themselves after the same, and the tap's waits all have timeouts.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from bench.faults import Tap, drain_stderr, free_port, plant_events, wall  # noqa: E402
from deploy import operator  # noqa: E402
from leader import profile  # noqa: E402
from tether import catalog, wire  # noqa: E402
from tether.node import load_mission  # noqa: E402
from tether.runfile import Run  # noqa: E402

MISSION = "section4"
CODE = {wire.FLYING: "F", wire.HOLD: "H", wire.LAND: "L", wire.LANDED: "LD", wire.ESTOP: "E"}
BOUND = 120.0
"""Seconds past ``--duration`` after which a run's launcher is killed and its busy loops end."""


def hogs(n: int, seconds: float) -> list[subprocess.Popen[bytes]]:
    """``n`` busy loops at the default policy, each ending by itself after ``seconds``."""
    burn = f"import time\nend = time.monotonic() + {seconds}\nwhile time.monotonic() < end: pass"
    return [subprocess.Popen([sys.executable, "-c", burn], stdin=subprocess.DEVNULL) for _ in range(n)]


def run_once(repo: Path, out: Path, priority: str, action: operator.Action, args: argparse.Namespace) -> dict[str, Any]:
    """One run beside ``args.hogs`` busy loops; the figures of the module's docstring."""
    load = os.getloadavg()[0]
    busy = hogs(args.hogs, args.duration + BOUND)
    port = free_port()
    ep = f"tls/127.0.0.1:{port}"
    cmd = [sys.executable, "-m", "cli", "run", MISSION, "--clock", "realtime", "--out", str(out),
           "--duration", repr(args.duration), "--quiet", "--listen", ep]
    if priority != "none":
        cmd += ["--rt-priority", priority]
    lines: list[str] = []
    res: dict[str, Any] = {"priority": priority, "load": load, "hogs": args.hogs, "order": action}
    try:
        time.sleep(1.0)  # the busy loops are running before the swarm starts
        launcher = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=repo)

        th = drain_stderr(launcher, lines.append)
        tap = Tap(ep, MISSION, out / "tls" / "control-0.json5")
        order: dict[str, Any] = {}
        try:
            try:
                tap.open(timeout=60.0)
                tap.declare_order_publisher()
            except Exception as exc:  # noqa: BLE001 - a gateway that never answers is a figure of the run
                res["tap_error"] = f"{type(exc).__name__}: {exc}"[:200]
            deadline = wall() + 90
            while tap.session is not None and tap.epoch is None and wall() < deadline and launcher.poll() is None:
                time.sleep(0.01)
            if tap.epoch is not None:
                time.sleep(max(0.0, tap.epoch + args.order_at - wall()))
                if args.cli:
                    order["start"] = wall()
                    r = subprocess.run([sys.executable, "-m", "cli", action, "--ns", MISSION, "--zenoh-config",
                                        str(out / "tls" / "control-0.json5"), "--reason", "bench/loaded.py"],
                                       cwd=repo, capture_output=True, text=True, timeout=60)
                    order.update(wall=wall() - order["start"], status=r.returncode, err=r.stderr.strip()[-300:])
                else:
                    tap.send_order(action)
                    assert tap.order_put is not None
                    order["start"] = tap.order_put
            launcher.wait(args.duration + BOUND)
        except subprocess.TimeoutExpired:
            pass
        finally:
            if launcher.poll() is None:
                launcher.kill()
                launcher.wait()
            th.join(5)
            tap.close()
    finally:
        for h in busy:
            h.kill()
            h.wait()
    res["exit"] = launcher.returncode
    res["load_end"] = os.getloadavg()[0]
    (out / "launcher.log").write_text("\n".join(lines) + "\n")
    res.update(analyse(out, tap, action, order, args))
    return res


def first_report(tap: Tap, mode: int, since: float) -> dict[int, float]:
    """Per plant, the tap's arrival time of its first state in ``mode`` heard at or after ``since``."""
    first: dict[int, float] = {}
    for w, kind, vid, msg in tap.decoded():
        if kind == "plant/state" and w >= since and getattr(msg, "mode", None) == mode:
            first[vid] = min(w, first.get(vid, math.inf))
    return first


def analyse(out: Path, tap: Tap, action: str, order: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    m = load_mission(catalog.resolve(MISSION), args.duration)
    res: dict[str, Any] = {}
    gw = (out / "logs" / "gateway.log")
    said = [ln for ln in (gw.read_text(errors="replace").splitlines() if gw.exists() else []) if "CPU priority" in ln]
    res["gateway"] = said[0].split("CPU priority: ", 1)[1][:40] if said else "normal (no line)"
    sched_lines = [ln for ln in (out / "launcher.log").read_text().splitlines() if "CPU scheduling" in ln]
    res["launcher_sched"] = sched_lines[0].split("CPU scheduling", 1)[1][:160] if sched_lines else ""
    ids = sorted(a.id for a in m.agents)
    if "start" in order:
        got = first_report(tap, wire.LAND if action == "land" else wire.ESTOP, order["start"])
        res["latency"] = max(got.values()) - order["start"] if len(got) == len(ids) else math.nan
        res["reached"] = len(got)
        if "wall" in order:
            res["cmd"] = f"{order['wall']:.2f} s exit {order['status']}"
            if order["status"] != 0:
                res["cmd_err"] = order["err"]
    else:
        res["latency"], res["reached"] = math.nan, 0
    res["reach"] = math.nan
    if "start" in order and tap.epoch is not None and (out / "run.npz").exists():
        want = wire.LAND if action == "land" else wire.ESTOP
        try:
            got_at = {e.vehicle: e.t for e in reversed(Run.load(out).safety.plant_events) if e.dst == want}
        except Exception:  # noqa: BLE001 - analysed below, where the run file's absence is a figure
            got_at = {}
        if len(got_at) == len(ids):
            res["reach"] = max(got_at.values()) - (order["start"] - tap.epoch)
    try:
        run = Run.load(out)
    except Exception as exc:  # noqa: BLE001 - a run without a file is a figure too
        res.update(late=math.nan, events=[f"no run file ({type(exc).__name__})"], sep=math.nan, sep_fs=math.nan,
                   err=math.nan, err0=math.nan)
        return res
    h = m.dt
    T = len(run.t)
    late = run.runtime.late if run.runtime is not None else np.full((T, len(ids)), np.nan)
    counts = [float(c[np.isfinite(c)][-1]) for c in late.T if np.isfinite(c).any()]
    res["late"] = sum(counts) / (len(counts) * T) if counts else math.nan
    evs = [(e.t, "a", e.vehicle, e.src, e.dst, e.reason) for e in run.safety.events if e.src != e.dst]
    pev = [(e.t, "p", e.vehicle, e.src, e.dst, e.reason) for e in run.safety.plant_events if e.src != e.dst] \
        if run.safety.plant_events else [(t, "p", v, s, d, why) for t, v, s, d, why in plant_events(out)]
    before = sorted(e for e in evs + pev if e[0] < args.order_at - h / 2)
    res["events"] = [f"{t:.2f} {w}{v} {CODE.get(s, s)}>{CODE.get(d, d)} {why}" for t, w, v, s, d, why in before]
    P = run.runtime.plant_p if run.runtime is not None else run.p
    k_fs = int(round(before[0][0] / h)) if before else None
    sep, sep_fs = math.inf, math.inf
    for k in range(T):
        pk = P[k]
        for i in range(len(ids)):
            for j in range(i + 1, len(ids)):
                d = float(np.linalg.norm(pk[i] - pk[j]))
                if math.isfinite(d):
                    sep = min(sep, d)
                    if k_fs is not None and k >= k_fs:
                        sep_fs = min(sep_fs, d)
    res["sep"], res["sep_fs"] = sep, (sep_fs if k_fs is not None else math.nan)
    ref = profile.build(m.leader, m.dim)
    pl = np.asarray(ref(run.t)[0]).reshape(T, m.dim)
    offsets = np.array([next(a.offset for a in m.agents if a.id == v) for v in ids], dtype=float)
    err = np.linalg.norm(P - offsets[None] - pl[:, None, :], axis=2)  # (T, N)
    k_order = min(T, int(args.order_at / h))
    half = err[k_order // 2:k_order]
    res["err"] = float(np.nanmax(half)) if np.isfinite(half).any() else math.nan
    first = err[: min(k_order, int(10 / h))]
    res["err0"] = float(np.nanmax(first)) if np.isfinite(first).any() else math.nan
    return res


def fmt(x: float, digits: int = 3) -> str:
    return "nan" if not math.isfinite(x) else f"{x:.{digits}f}"


def med(rows: list[dict[str, Any]], key: str) -> float:
    xs = [r[key] for r in rows if isinstance(r[key], float) and math.isfinite(r[key])]
    return statistics.median(xs) if xs else math.nan


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hogs", type=int, default=2, help="busy loops beside the swarm (default 2)")
    p.add_argument("--reps", type=int, default=4, help="runs of each configuration (default 4: land, estop, land, estop)")
    p.add_argument("--priorities", nargs="+", default=["none", "10"],
                   help="'none' (no option: the launcher's default) or an --rt-priority value, each a configuration")
    p.add_argument("--duration", type=float, default=25.0, help="mission seconds (default 25)")
    p.add_argument("--order-at", type=float, default=18.0, help="mission time of the operator's order [s] (default 18)")
    p.add_argument("--cli", action="store_true",
                   help="send the order with the real command (tether land|estop --zenoh-config), timed from its start")
    p.add_argument("--repo", type=Path, default=REPO, help="the checkout whose tether runs (default this one)")
    p.add_argument("--compare", type=Path, default=None,
                   help="also run each configuration on this checkout (labelled b:...), alternating with --repo's")
    p.add_argument("--keep", type=Path, default=None, help="keep every run's directory under this one")
    p.add_argument("--json", type=Path, default=None, help="write every run's figures here")
    args = p.parse_args(argv)
    if not 0 < args.order_at < args.duration:
        p.error("need 0 < --order-at < --duration")
    configs = [(f"a:{pr}" if args.compare else pr, args.repo, pr) for pr in args.priorities]
    if args.compare is not None:
        configs += [(f"b:{pr}", args.compare, pr) for pr in args.priorities]
    rows: dict[str, list[dict[str, Any]]] = {label: [] for label, _, _ in configs}
    print(f"section4 realtime {args.duration:g} s beside {args.hogs} busy loops, {os.cpu_count()} CPUs, "
          f"tether from {args.repo}{' (a) and ' + str(args.compare) + ' (b)' if args.compare else ''}, orders by {'the command' if args.cli else 'the tap'}", flush=True)
    with tempfile.TemporaryDirectory(prefix="loaded-") as tmp:
        work = args.keep or Path(tmp)
        for rep in range(args.reps):
            action: operator.Action = "land" if rep % 2 == 0 else "estop"
            for label, repo, pr in configs:
                r = run_once(repo.resolve(), work / f"{label.replace(':', '-')}-{rep}", pr, action, args)
                rows[label].append(r)
                print(f"[{label:>4} #{rep}] load {r['load']:.1f} exit {r['exit']} late {100 * r['late']:.1f} % "
                      f"sep {fmt(r['sep'])} m (from the first failsafe {fmt(r['sep_fs'])}) err {fmt(r['err'])} m "
                      f"{action} reached {fmt(r['reach'], 2)} s, seen {fmt(r['latency'], 2)} s ({r['reached']}/4{', ' + r['cmd'] if 'cmd' in r else ''}) "
                      f"gateway {r['gateway']}; launcher{r['launcher_sched']}", flush=True)
                for line in r["events"][:12]:
                    print(f"      {line}", flush=True)
                if len(r["events"]) > 12:
                    print(f"      ... {len(r['events']) - 12} more", flush=True)
                for key in ("cmd_err", "tap_error"):
                    if key in r:
                        print(f"      {key}: {r[key]}", flush=True)
                if r["exit"] not in (0, 3, 5):
                    tail = (work / f"{label.replace(':', '-')}-{rep}" / "launcher.log").read_text().splitlines()[-4:]
                    print("      launcher: " + "\n      launcher: ".join(tail), flush=True)
    print("\nmedians over the runs (failsafes: runs with any mode change before the order / runs)")
    print("| configuration | load | late ticks | failsafes | events (median) | min sep [m] | err [m] "
          "| land reached / seen [s] | estop reached / seen [s] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for pr, rs in rows.items():
        n_fs = sum(1 for r in rs if r["events"])
        by = {a: [r for r in rs if r["order"] == a] for a in ("land", "estop")}
        print(f"| {pr} | {med(rs, 'load'):.1f} | {100 * med(rs, 'late'):.1f} % | {n_fs}/{len(rs)} | "
              f"{statistics.median(len(r['events']) for r in rs):g} | {fmt(med(rs, 'sep'))} | {fmt(med(rs, 'err'))} | "
              f"{fmt(med(by['land'], 'reach'), 2)} / {fmt(med(by['land'], 'latency'), 2)} | "
              f"{fmt(med(by['estop'], 'reach'), 2)} / {fmt(med(by['estop'], 'latency'), 2)} |")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
