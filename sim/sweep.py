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
formation error non-finite or beyond :data:`sim.setup.DIVERGE_AT`), and what the links did
(delivery ratio, age of the neighbour data used, p50 and p99).
"""

from __future__ import annotations

import csv
import math
import os
import subprocess
import sys
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
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
from sim.setup import DIVERGE_AT
from tether.runfile import Run

Engine = Literal["inprocess", "runtime"]
LAWS = ("sigma", "benchmark")


class SweepError(ValueError):
    """A bad grid: names the option and the fix."""


@dataclass(frozen=True)
class Point:
    """One cell of a study: a law, a network, optionally the law's sigma and rates (None: the
    mission's) and a Monte Carlo replicate (None: the mission itself; ``sim.study.replicate``)."""

    law: str
    loss_pct: float
    delay_ms: float
    burst: float
    sigma: float | None = None
    gamma_p: float | None = None
    gamma_v: float | None = None
    rep: int | None = None

    @property
    def name(self) -> str:
        text = f"{self.law}-loss{self.loss_pct:g}-delay{self.delay_ms:g}-burst{self.burst:g}"
        for tag, x in (("sigma", self.sigma), ("gp", self.gamma_p), ("gv", self.gamma_v)):
            if x is not None:
                text += f"-{tag}{x:g}"
        return text if self.rep is None else f"{text}-rep{self.rep}"


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
                  compensate: bool | None = None, p0_jitter: float = 0.0) -> ms.Mission:
    """The mission of one grid point: ``m`` under ``pt.law`` (with the point's sigma and rates
    when set) with the point's network everywhere (and ``[links] compensate`` set when
    ``compensate`` is given), as replicate ``pt.rep`` when set (start positions jittered by up to
    ``p0_jitter`` m)."""
    if m.law.kind == "custom":  # a law of one's own: run as it is, with the point's network
        if pt.law != "custom":
            raise SweepError(f"--laws: this mission runs its own law ({m.law.use}), which cannot become {pt.law!r}; "
                             "give --laws custom")
        if pt.sigma is not None or pt.gamma_p is not None or pt.gamma_v is not None:
            raise SweepError("--sigma, --gamma-p, --gamma-v: this mission runs its own law "
                             f"({m.law.use}); set its parameters in the mission's [law] params")
    elif pt.law not in LAWS:
        raise SweepError(f"--laws: {pt.law!r} is not a law; use sigma, benchmark or both")
    if pt.law == "benchmark" and pt.sigma is not None:
        raise SweepError("--sigma: the benchmark law has no sigma; give --laws sigma with a --sigma grid")
    if pt.law == "sigma" and m.law.kind != "sigma" and pt.sigma is None:
        raise SweepError("--laws: this mission's law is the benchmark, which does not say which sigma to use; "
                         "give --sigma or --laws benchmark")
    if m.law.kind != "sigma" and pt.law == "sigma":
        base = msgspec.structs.replace(m, law=msgspec.structs.replace(m.law, kind="sigma", sigma=pt.sigma))
    else:
        base = m if pt.law == m.law.kind else with_law(m, pt.law)
    changes = {k: v for k, v in (("sigma", pt.sigma), ("gamma_p", pt.gamma_p), ("gamma_v", pt.gamma_v))
               if v is not None}
    if changes:
        base = msgspec.structs.replace(base, law=msgspec.structs.replace(base.law, **changes))
    if pt.rep is not None:
        from sim import study

        base = study.replicate(base, pt.rep, p0_jitter)
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
        "gain_convergence_s": gain_convergence_time(run.t, run.kp, run.kv),
        "peak_kp": s["peak_kp"],
        "peak_kv": s["peak_kv"],
        "final_kp_mean": s["final_kp_mean"],
        "final_kv_mean": s["final_kv_mean"],
        "kp_growth_per_s": s["kp_growth_per_s"],
        "kv_growth_per_s": s["kv_growth_per_s"],
        "max_xi_m": s["max_xi_m"],
        "diverged": bool(s["diverged"] or run.meta.diverged_at is not None
                         or not true_max <= DIVERGE_AT),
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


GAIN_TOL = 0.05
"""A gain has converged once it stays within this fraction of its final value."""

METRICS_VERSION = 3
"""Changes whenever a figure of merit's definition does: part of every cell's identity, so a study
made with other definitions is not resumed into this one (1: no ``gain_convergence_s``; 2: it,
against the final sample; 3: against the tail's mean, so that gains that settle into a ripple have
one)."""


def gain_convergence_time(t: np.ndarray, kp: np.ndarray, kv: np.ndarray, tol: float = GAIN_TOL,
                          tail: float = 0.1) -> float:
    """The first sample time after which every agent's every gain (``Kp`` and ``Kv``, each axis)
    stays within ``tol`` of its settled value [s], the settled value being its mean over the last
    ``tail`` of the run (a gain of the sigma law settles into a ripple that the disturbances keep up,
    so its final sample is no settled value). NaN when a gain has no settled value: its mean moves by
    more than ``tol / 5`` of it between the two halves of the tail (the gains grow without bound, or
    the run is too short to tell), or its ripple in the tail leaves the band; also when the run
    diverged."""
    k = np.concatenate([kp.reshape(len(t), -1), kv.reshape(len(t), -1)], axis=1)
    if not np.all(np.isfinite(k)):
        return math.nan
    i0 = min(len(t) - 2, int(math.floor(len(t) * (1.0 - tail))))
    last = k[i0:]
    half = len(last) // 2
    settled = last.mean(axis=0)
    if np.any(np.abs(last[half:].mean(axis=0) - last[:half].mean(axis=0)) > 0.2 * tol * np.abs(settled)):
        return math.nan
    bad = np.nonzero(~np.all(np.abs(k - settled) <= tol * np.abs(settled), axis=1))[0]
    if bad.size == 0:
        return float(t[0])
    first = bad[-1] + 1
    if first > i0:  # the band is left within the tail itself
        return math.nan
    return float(t[first])


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


POINT_COLUMNS = ("law", "loss_pct", "delay_ms", "burst", "sigma", "gamma_p", "gamma_v", "rep", "seed")
COLUMNS = (*POINT_COLUMNS, "ultimate_bound_m", "ultimate_bound_seen_m", "max_xi_true_m",
           "settling_time_s", "peak_gain", "gain_convergence_s", "peak_kp",
           "peak_kv", "final_kp_mean", "final_kv_mean", "kp_growth_per_s", "kv_growth_per_s", "max_xi_m",
           "diverged", "diverged_at_s", "failsafe_at_s", "grounded", "delivery_ratio", "age_p50_ms", "age_p99_ms")
"""``sweep.csv``: what was run and what it gave; nothing about where or how long (``study.jsonl``
has each cell's worker and wall time), so the same study gives the same file on any executor."""

MC_METRICS = ("ultimate_bound_m", "ultimate_bound_seen_m", "max_xi_true_m", "settling_time_s", "peak_gain",
              "gain_convergence_s", "final_kp_mean", "final_kv_mean", "kp_growth_per_s", "delivery_ratio",
              "age_p99_ms")
"""The metrics a Monte Carlo study summarises per cell (``summary.csv``)."""

GROUP = ("law", "loss_pct", "delay_ms", "burst", "sigma", "gamma_p", "gamma_v")

P0_JITTER_M = 0.2
"""A Monte Carlo replicate's default start-position jitter [m] per horizontal axis."""


class StudyFailed(RuntimeError):
    """Some cells raised (or their workers kept dying): the others are kept; rerunning retries them."""

    def __init__(self, failed: dict[str, str], done: int, total: int) -> None:
        first = next(iter(failed.items()))
        super().__init__(f"{len(failed)} of {total} cells failed ({done} done and kept); first: {first[0]}: "
                         f"{first[1][:300]}; rerun the same command to retry them")
        self.failed = failed


def points_of(m: ms.Mission, *, loss: Sequence[float], delay: Sequence[float], burst: Sequence[float],
              laws: Sequence[str], sigma: Sequence[float] | None = None, gamma_p: Sequence[float] | None = None,
              gamma_v: Sequence[float] | None = None, seeds: int | None = None) -> list[Point]:
    """Every cell of a study, in table order (replicates innermost)."""
    reps: Sequence[int | None] = [None] if seeds is None else range(seeds)
    sig: Sequence[float | None] = sigma or [None]
    gps: Sequence[float | None] = gamma_p or [None]
    gvs: Sequence[float | None] = gamma_v or [None]
    return [Point(law, lo, de, b, s, gp, gv, r)
            for law in laws for b in burst for lo in loss for de in delay
            for s in sig for gp in gps for gv in gvs for r in reps]


def sweep(m: ms.Mission, out: Path, *, loss: list[float], delay: list[float], burst: Sequence[float] = (1.0,),
          laws: tuple[str, ...] = LAWS, jitter_ms: float = 0.0, duration: float | None = None,
          engine: Engine = "inprocess", jobs: int = 1, compensate: bool | None = None,
          progress: Callable[..., None] | None = None, sigma: Sequence[float] | None = None,
          gamma_p: Sequence[float] | None = None, gamma_v: Sequence[float] | None = None,
          seeds: int | None = None, p0_jitter: float = P0_JITTER_M, executor: str | None = None,
          connect_timeout: float | None = None, stop_after: int | None = None, on_start: Callable[[int, str], None] | None = None) -> list[dict]:
    """Run the grid (every cell through :mod:`sim.study`: kept as it finishes in ``study.jsonl``, a
    rerun resumes), write ``sweep.csv``, ``sweep.json``, ``sweep.md``, the figures (and with
    ``seeds``, ``summary.csv``) and every point's mission file under ``out``; returns the rows (in
    grid order). ``executor``: None (inline for ``jobs = 1``, else a local pool) or a Dask
    scheduler's ``tcp://HOST:PORT``. ``on_start(cells, executor_kind)`` is called once the executor
    is up, before the first cell; ``stop_after``: interrupt after that many cells (measurements)."""
    from sim import study, studyplots

    if engine not in ("inprocess", "runtime"):
        raise SweepError(f"--engine: {engine!r} is not an engine; use inprocess or runtime")
    if jobs < 1:
        raise SweepError(f"--jobs: {jobs} must be at least 1")
    if executor is not None and engine == "runtime":
        raise SweepError("--executor: the runtime engine writes each point's run file on the machine that runs "
                         "it; use --engine inprocess with --executor")
    if m.law.kind == "custom" and tuple(laws) == LAWS:  # the paper's two laws by default; a law of one's own alone
        laws = ("custom",)
    points = points_of(m, loss=loss, delay=delay, burst=burst, laws=laws, sigma=sigma, gamma_p=gamma_p,
                       gamma_v=gamma_v, seeds=seeds)
    if len(points) > study.MAX_CELLS:
        raise SweepError(f"--seeds: the study has {len(points)} cells, more than {study.MAX_CELLS} "
                         f"({study.estimate(m, len(points))}); use fewer seeds or a smaller grid")
    missions = {pt: point_mission(m, pt, jitter_ms, duration, compensate, p0_jitter) for pt in points}
    texts = {pt: ms.dumps(pm) for pt, pm in missions.items()}
    cells = {pt: study.Cell(pt.name, texts[pt], engine, f"metrics {METRICS_VERSION}") for pt in points}
    meta = {"mission": m.name, "engine": engine, "duration_s": duration if duration is not None else m.duration,
            "rate_hz": m.rate, "seed": m.seed, "loss_pct": list(loss), "delay_ms": list(delay),
            "burst": list(burst), "jitter_ms": jitter_ms, "laws": list(laws),
            "sigma": list(sigma) if sigma else None, "gamma_p": list(gamma_p) if gamma_p else None,
            "gamma_v": list(gamma_v) if gamma_v else None, "seeds": seeds,
            "p0_jitter_m": p0_jitter if seeds else None,
            "max_age_s": m.links.max_age, "compensate": m.links.compensate if compensate is None else compensate}
    cell_list = [cells[pt] for pt in points]
    dirs = {cells[pt].digest: str(out / "points" / pt.name) for pt in points}
    results = study.StudyFile(out / "study.jsonl")
    results.check(study.study_key(cell_list))  # another study's directory is left as it is
    timeout = study.CONNECT_TIMEOUT_S if connect_timeout is None else connect_timeout
    with study.open_executor(executor, jobs, timeout) as eng:  # a bad --executor stops here, before anything is written
        out.mkdir(parents=True, exist_ok=True)
        for pt, text in texts.items():
            d = out / "points" / pt.name
            d.mkdir(parents=True, exist_ok=True)
            f = d / "mission.toml"
            if not f.exists() or f.read_text() != text:
                f.write_text(text)
        if on_start is not None:
            on_start(len(points), eng.kind)
        outcome = study.run(cell_list, results, eng, run_point, meta=meta, workdir=lambda c: dirs[c.digest],
                            progress=progress, stop_after=stop_after)
    if outcome.failed:
        raise StudyFailed(outcome.failed, len(outcome.records), len(points))
    ordered = []
    for pt in points:
        law = missions[pt].law
        ordered.append({"law": pt.law, "loss_pct": pt.loss_pct, "delay_ms": pt.delay_ms, "burst": pt.burst,
                        "sigma": law.sigma, "gamma_p": law.gamma_p, "gamma_v": law.gamma_v, "rep": pt.rep,
                        "seed": missions[pt].seed, **outcome.records[cells[pt].digest]["row"]})
    walls = [r["wall_s"] for r in outcome.records.values()]
    meta["cells"] = len(points)
    meta["cell_wall_s_median"] = float(np.median(walls)) if walls else None
    meta["ran_now"], meta["resumed"] = outcome.ran, outcome.resumed
    meta["per_worker"] = dict(outcome.per_worker)
    meta["executor"] = eng.kind
    _write_csv(out / "sweep.csv", ordered, COLUMNS)
    summary = None
    if seeds is not None:
        summary = study.summarise(ordered, GROUP, MC_METRICS)
        cols = [*GROUP, "replicates", "diverged"] + [f"{k}_{s}" for k in MC_METRICS
                                                     for s in ("mean", "std", "ci_lo", "ci_hi", "n")]
        _write_csv(out / "summary.csv", summary, tuple(cols))
    (out / "sweep.json").write_text(jsonout.dumps({"meta": meta, "rows": ordered, "summary": summary}))
    title = f"{m.name}: {meta['duration_s']:g} s"
    plain = sigma is None and gamma_p is None and gamma_v is None and seeds is None
    if plain:
        from sim import figures

        paths = figures.heatmaps(ordered, out, loss=loss, delay=delay, burst=list(burst), laws=list(laws),
                                 title=f"{title}, swarm-wide link impairment")
        (out / "sweep.md").write_text(report(ordered, meta, paths))
    else:
        paths = studyplots.study_figures(ordered, summary, out, meta, title=title)
        (out / "sweep.md").write_text(studyplots.report(ordered, summary, meta, paths))
    return ordered


def _write_csv(path: Path, rows: list[dict], columns: tuple[str, ...]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
        w.writeheader()
        for row in rows:
            w.writerow({k: _csv(row.get(k)) for k in columns})
    os.replace(tmp, path)


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
