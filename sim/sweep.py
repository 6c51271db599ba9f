"""Degradation studies: one mission run over a grid of link loss, delay and burstiness, for both laws.

Every point of the grid is the mission with a swarm-wide ``[netem]`` default (every directed link,
the leader's included) of

* ``delay = { constant = delay_ms / 1000, jitter = jitter_ms / 1000 }``;
* loss ``L = loss_pct / 100``: Bernoulli ``p = L`` when ``burst = 1``; otherwise Gilbert-Elliott
  with mean burst length ``b`` messages, ``r = 1/b``, ``p = L r / (1 - L)``, ``bad_loss = 1``,
  ``good_loss = 0``, whose stationary loss ratio is ``p / (p + r) = L``.

Each point runs under the lockstep semantics (delays in simulated time, reproducible for the
mission's seed) either in one process (``engine = "inprocess"``: :mod:`sim.lockstep`, equal to
the runtime bit for bit) or as real processes over Zenoh (``engine = "runtime"``: ``tether run``).
The mission file of every point is written beside the results, so any cell can be re-run alone.

Figures of merit (``docs/metrics.md``): the ultimate bound of the *true* formation error
``||xi||`` (Eq. 8 from the vehicles' positions) over the last 10 % of the run, and of the ``xi`` the
agents computed from the (old, lost, substituted) data they had; the peak gain ``max(Kp, Kv)``, the gains' growth rate over the second half, divergence (the
formation error non-finite or beyond :data:`sim.lockstep.DIVERGE_AT`), and what the links did
(delivery ratio, age of the neighbour data used, p50 and p99).
"""

from __future__ import annotations

import csv
import math
import os
import subprocess
import sys
import threading
import time
import warnings
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Callable, Literal

import msgspec
import numpy as np

from tether import jsonout
from tether.netprofile import Bernoulli, Delay, GilbertElliott, LinkProfile, Network
from tether import graph, wire
from sim import lockstep, metrics
from tether import mission as ms
from sim.reproduce import with_law
from tether.runfile import Run

Engine = Literal["inprocess", "runtime"]
LAWS = ("sigma", "benchmark")


class SweepError(ValueError):
    """A bad grid: names the option and the fix."""


@dataclass(frozen=True)
class Point:
    law: str
    loss_pct: float
    delay_ms: float
    burst: float

    @property
    def name(self) -> str:
        return f"{self.law}-loss{self.loss_pct:g}-delay{self.delay_ms:g}-burst{self.burst:g}"


def parse_list(text: str, option: str, lo: float, hi: float, unit: str, hi_open: bool = False) -> list[float]:
    """``"0,10,30"`` -> ``[0.0, 10.0, 30.0]``; each value finite and in ``[lo, hi]`` (``hi``
    excluded when ``hi_open``); raises :class:`SweepError` naming ``option``."""
    values = []
    for item in text.split(","):
        try:
            x = float(item)
        except ValueError:
            raise SweepError(f"{option}: {item.strip()!r} is not a number; give a comma-separated list "
                             f"such as {option} 0,10,30 [{unit}]") from None
        bad_hi = x >= hi if hi_open else x > hi
        if not math.isfinite(x) or x < lo or bad_hi:
            bound = f"below {hi:g}" if hi_open else f"at most {hi:g}"
            raise SweepError(f"{option}: {x:g} is out of range; each value must be >= {lo:g} and {bound} [{unit}]")
        values.append(x)
    if len(set(values)) != len(values):
        raise SweepError(f"{option}: {text} repeats a value; list each value once")
    return values


def link_profile(loss_pct: float, delay_ms: float, burst: float, jitter_ms: float = 0.0) -> LinkProfile:
    """The profile of every link at one grid point (see the module docstring)."""
    loss_ratio = loss_pct / 100.0
    loss: Bernoulli | GilbertElliott
    if burst <= 1.0 or loss_ratio == 0.0:
        loss = Bernoulli(p=loss_ratio)
    else:
        r = 1.0 / burst
        loss = GilbertElliott(p=min(1.0, loss_ratio * r / (1.0 - loss_ratio)), r=r, bad_loss=1.0, good_loss=0.0)
    return LinkProfile(delay=Delay(constant=delay_ms / 1000.0, jitter=jitter_ms / 1000.0), loss=loss)


def point_mission(m: ms.Mission, pt: Point, jitter_ms: float = 0.0, duration: float | None = None,
                  compensate: bool | None = None) -> ms.Mission:
    """The mission of one grid point: ``m`` under ``pt.law`` with the point's network everywhere
    (and ``[links] compensate`` set when ``compensate`` is given)."""
    if pt.law not in LAWS:
        raise SweepError(f"--laws: {pt.law!r} is not a law; use sigma, benchmark or both")
    base = m if pt.law == m.law.kind else with_law(m, pt.law)
    net = Network(default=link_profile(pt.loss_pct, pt.delay_ms, pt.burst, jitter_ms))
    out = msgspec.structs.replace(base, netem=net, name=f"{m.name}-{pt.name}")
    if duration is not None:
        out = msgspec.structs.replace(out, duration=duration)
    if compensate is not None:
        out = msgspec.structs.replace(out, links=msgspec.structs.replace(out.links, compensate=compensate))
    problems = ms.validate(out)
    if problems:
        raise SweepError("; ".join(f"{f} {msg}" for f, msg in problems))
    return out


def figures_of_merit(run: Run, m: ms.Mission) -> dict[str, float | bool | None]:
    """One row of the table from a run (in-process or recorded) of mission ``m``."""
    with warnings.catch_warnings():  # a diverged run's tail is all NaN: its bound is NaN, said so
        warnings.simplefilter("ignore", RuntimeWarning)
        s = metrics.summary(run)
        true = np.linalg.norm(metrics.formation_error(run, graph.topology(m).adjacency,
                                                      np.array([a.offset for a in m.agents], dtype=float)), axis=2)
        true_bound = float(np.nanmax(true[metrics.tail_slice(run, 0.1)]))
        true_max = float(np.nanmax(true))
    row: dict[str, float | bool | None] = {
        "ultimate_bound_m": true_bound,
        "max_xi_true_m": true_max,
        "ultimate_bound_seen_m": s["ultimate_bound_xi_m"],
        "settling_time_s": s["settling_time_s"],
        "peak_gain": max(s["peak_kp"], s["peak_kv"]),
        "peak_kp": s["peak_kp"],
        "peak_kv": s["peak_kv"],
        "final_kp_mean": s["final_kp_mean"],
        "final_kv_mean": s["final_kv_mean"],
        "kp_growth_per_s": s["kp_growth_per_s"],
        "kv_growth_per_s": s["kv_growth_per_s"],
        "max_xi_m": s["max_xi_m"],
        "diverged": bool(s["diverged"] or run.meta.diverged_at is not None
                         or not true_max <= lockstep.DIVERGE_AT),
        "diverged_at_s": run.meta.diverged_at,
        # the safety layer's part: when its first event came, and how many vehicles it grounded
        "failsafe_at_s": run.safety.events[0].t if run.safety.events else None,
        "grounded": int(np.sum(np.isin(run.safety.safety_mode[_last_row(run.safety.safety_mode)],
                                       (wire.LAND, wire.LANDED, wire.ESTOP)))),
    }
    if run.links is not None:
        ticks = len(run.t)
        mask = run.links.src > 0
        received = run.links.final(run.links.received)  # recorded: cumulative per tick
        row["delivery_ratio"] = float(received[mask].sum() / (mask.sum() * ticks))
        age = run.links.age[:, mask]
        age = age[np.isfinite(age)]
        row["age_p50_ms"] = float(np.percentile(age, 50) * 1e3) if age.size else math.nan
        row["age_p99_ms"] = float(np.percentile(age, 99) * 1e3) if age.size else math.nan
    return row


def _last_row(modes: np.ndarray) -> int:
    """The last tick with every vehicle's mode recorded (-1 marks no sample; a diverged run stops early)."""
    rows = np.nonzero(np.all(modes >= 0, axis=1))[0]
    return int(rows[-1]) if rows.size else len(modes) - 1


def run_point(mission_text: str, engine: Engine, workdir: str | None) -> dict:
    """Run one grid point (in a worker process) and return its row. ``mission_text``: TOML."""
    m = ms.loads(mission_text, source="<sweep point>")
    t0 = time.perf_counter()
    if engine == "inprocess":
        run = lockstep.simulate(m)
    else:
        if workdir is None:
            raise ValueError("the runtime engine needs a work directory")
        out = Path(workdir)
        path = out / "mission.toml"
        r = subprocess.run([sys.executable, "-m", "cli", "run", str(path), "--out", str(out), "--quiet"],
                           capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"tether run {path} failed with status {r.returncode}: {r.stderr[-2000:]}")
        run = Run.load(out)
    row = figures_of_merit(run, m)
    row["wall_s"] = time.perf_counter() - t0
    return row


COLUMNS = ("law", "loss_pct", "delay_ms", "burst", "ultimate_bound_m", "ultimate_bound_seen_m", "max_xi_true_m",
           "settling_time_s", "peak_gain", "peak_kp",
           "peak_kv", "final_kp_mean", "final_kv_mean", "kp_growth_per_s", "kv_growth_per_s", "max_xi_m",
           "diverged", "diverged_at_s", "failsafe_at_s", "grounded", "delivery_ratio", "age_p50_ms", "age_p99_ms",
           "wall_s")


def sweep(m: ms.Mission, out: Path, *, loss: list[float], delay: list[float], burst: Sequence[float] = (1.0,),
          laws: tuple[str, ...] = LAWS, jitter_ms: float = 0.0, duration: float | None = None,
          engine: Engine = "inprocess", jobs: int = 1, compensate: bool | None = None,
          progress: Callable[[int, int, str], None] | None = None) -> list[dict]:
    """Run the grid, write ``sweep.csv``, ``sweep.json``, ``sweep.md``, the heatmaps and every
    point's mission file under ``out``; returns the rows (in grid order)."""
    from sim import figures

    if engine not in ("inprocess", "runtime"):
        raise SweepError(f"--engine: {engine!r} is not an engine; use inprocess or runtime")
    if jobs < 1:
        raise SweepError(f"--jobs: {jobs} must be at least 1")
    points = [Point(law, lo, de, b) for law in laws for b in burst for lo in loss for de in delay]
    texts = {pt: ms.dumps(point_mission(m, pt, jitter_ms, duration, compensate)) for pt in points}
    out.mkdir(parents=True, exist_ok=True)
    for pt, text in texts.items():
        d = out / "points" / pt.name
        d.mkdir(parents=True, exist_ok=True)
        (d / "mission.toml").write_text(text)
    rows: dict[Point, dict] = {}
    total = len(points)
    if progress is not None:
        progress(0, total, "sweep")
    if jobs == 1:
        for pt in points:
            rows[pt] = {**asdict(pt), **run_point(texts[pt], engine, str(out / "points" / pt.name))}
            if progress is not None:
                progress(len(rows), total, "sweep")
    else:  # spawned workers: a Zenoh session (runtime engine) must never cross a fork
        with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn"), initializer=_follow_parent,
                                 initargs=(os.getpid(),)) as pool:
            futures = {pool.submit(run_point, texts[pt], engine, str(out / "points" / pt.name)): pt for pt in points}
            for fut in as_completed(futures):
                pt = futures[fut]
                rows[pt] = {**asdict(pt), **fut.result()}
                if progress is not None:
                    progress(len(rows), total, "sweep")
    ordered = [rows[pt] for pt in points]
    with open(out / "sweep.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        w.writeheader()
        for row in ordered:
            w.writerow({k: _csv(row.get(k)) for k in COLUMNS})
    meta = {"mission": m.name, "engine": engine, "duration_s": duration if duration is not None else m.duration,
            "rate_hz": m.rate, "seed": m.seed, "loss_pct": loss, "delay_ms": delay, "burst": list(burst),
            "jitter_ms": jitter_ms, "laws": list(laws), "cpu_count": os.cpu_count(),
            "max_age_s": m.links.max_age, "compensate": m.links.compensate if compensate is None else compensate}
    (out / "sweep.json").write_text(jsonout.dumps({"meta": meta, "rows": ordered}))
    paths = figures.heatmaps(ordered, out, loss=loss, delay=delay, burst=list(burst), laws=list(laws),
                             title=f"{m.name}: {meta['duration_s']:g} s, swarm-wide link impairment")
    (out / "sweep.md").write_text(report(ordered, meta, paths))
    return ordered


def _follow_parent(pid: int) -> None:
    """In a worker: exit as soon as the sweep that started it is gone (killed, not just interrupted)."""
    def watch() -> None:
        while os.getppid() == pid:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="follow-parent").start()


def _csv(x: object) -> object:
    if x is None:
        return ""
    if isinstance(x, float):
        return f"{x:.6g}"
    return x


def report(rows: list[dict], meta: dict, figures: list[Path]) -> str:
    """``sweep.md``: the grid as tables, one per law and burst length (computed, not written)."""
    lines = [f"# Degradation sweep of `{meta['mission']}`", "",
             f"{meta['engine']} lockstep engine, {meta['duration_s']:g} s at {meta['rate_hz']:g} Hz, seed {meta['seed']}; "
             f"every link (the leader's included) delayed by the column's constant delay"
             + (f" ± {meta['jitter_ms']:g} ms uniform jitter" if meta["jitter_ms"] else "")
             + " and losing the row's share of messages; agents use neighbour data up to "
             f"{meta['max_age_s']:g} s old, " + ("with" if meta["compensate"] else "without")
             + " latency compensation. Definitions: docs/netem.md (Degradation studies).", ""]
    lines += [f"![{p.stem}]({p.name})" for p in figures]
    for law in meta["laws"]:
        for b in meta["burst"]:
            sub = [r for r in rows if r["law"] == law and r["burst"] == b]
            lines += ["", f"## {law} law, " + ("independent losses" if b <= 1 else f"loss bursts of {b:g} messages"), "",
                      "ultimate bound of the true ‖ξ‖ (as the agents saw it) [m] / peak gain (✗: diverged)", "",
                      "| loss \\ delay | " + " | ".join(f"{d:g} ms" for d in meta["delay_ms"]) + " |",
                      "|---" * (len(meta["delay_ms"]) + 1) + "|"]
            for lo in meta["loss_pct"]:
                cells = []
                for de in meta["delay_ms"]:
                    r = next(x for x in sub if x["loss_pct"] == lo and x["delay_ms"] == de)
                    cells.append(f"✗ at {r['diverged_at_s']:.4g} s" if r["diverged"]
                                 else f"{r['ultimate_bound_m']:.3g} ({r['ultimate_bound_seen_m']:.3g}) / "
                                      f"{r['peak_gain']:.3g}")
                lines.append(f"| {lo:g} % | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
