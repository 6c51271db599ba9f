"""Figures of merit of a run. Pure numpy over :class:`~tether.runfile.Run` arrays.

Definitions (also in ``docs/metrics.md``):

* ``xi_norm``: ``||xi_i(t_k)||`` per agent, shape ``(T, N)``.
* ultimate bound: ``max_i max_{t in tail} ||xi_i(t)||`` over the last ``tail`` fraction of the run.
* settling time: the first sample time after which ``max_i ||xi_i||`` stays at or below
  ``settle_factor`` times the ultimate bound (NaN if it never does).
* peak / final gains: max over the run / mean over agents and axes at the last sample.
* gain growth rate: least-squares slope of the agents' mean ``Kp`` (and ``Kv``) over the last half
  of the run [1/s]; about 0 when the gains are bounded, positive while they drift.
* tracking error: ``max_i ||p_i - h_i - p_leader||`` over the tail [m] (needs the offsets).
* true formation error: Eq. 8 from the recorded positions (:func:`formation_error`), against the
  ``xi`` the agents computed from the neighbour data they had.

A recorder's run may lack ticks (a run stopped early, a recorder frozen or killed: their modes read
-1). :func:`summary` is taken over the ticks that hold every agent's telemetry (:func:`recorded`):
a missing sample is not a divergence, and the tail and final values are those of the last ticks
recorded. The engines' runs hold every tick, so for them nothing changes.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from tether.runfile import NO_SAMPLE, Run


def xi_norm(run: Run) -> np.ndarray:
    return np.linalg.norm(run.xi, axis=2)


def tail_slice(run: Run, tail: float) -> slice:
    """The samples of the last ``tail`` fraction of the run."""
    n = len(run.t)
    return slice(min(n - 1, int(math.floor(n * (1.0 - tail)))), n)


def ultimate_bound(run: Run, tail: float = 0.1) -> float:
    return float(np.nanmax(xi_norm(run)[tail_slice(run, tail)]))


def settling_time(run: Run, tail: float = 0.1, settle_factor: float = 1.1) -> float:
    band = settle_factor * ultimate_bound(run, tail)
    worst = np.nanmax(xi_norm(run), axis=1)
    above = np.nonzero(worst > band)[0]
    if len(above) == 0:
        return float(run.t[0])
    last = above[-1]
    return float(run.t[last + 1]) if last + 1 < len(run.t) else math.nan


def growth_rate(t: np.ndarray, k: np.ndarray) -> float:
    """Slope [1/s] of the agents' mean gain over the last half of the run."""
    half = len(t) // 2
    mean = k[half:].reshape(len(t) - half, -1).mean(axis=1)
    tt = t[half:]
    if len(tt) < 2:
        return math.nan
    return float(np.polyfit(tt - tt[0], mean, 1)[0])


def tracking_error(run: Run, offsets: np.ndarray, tail: float = 0.1) -> float:
    """``max_i ||p_i - h_i - p_leader||`` over the tail [m]; ``offsets`` is ``(N, d)``."""
    e = run.p - offsets[None] - run.leader_p[:, None, :]
    return float(np.nanmax(np.linalg.norm(e, axis=2)[tail_slice(run, tail)]))


def formation_error(run: Run, adjacency: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """The true formation error ``xi_i = sum_j a_ij ((p_i - h_i) - (p_j - h_j))`` (Eq. 8) of every
    agent at every tick, from the recorded positions, ``(T, N, d)``. It differs from the ``xi`` the
    agents computed (``run.xi``) when they used old or substituted neighbour data (a degraded
    network). ``adjacency`` is :attr:`tether.graph.Topology.adjacency` (leader last), ``offsets``
    the agents' ``h_i`` ``(N, d)``."""
    n = offsets.shape[0]
    e = np.concatenate([run.p - offsets[None], run.leader_p[:, None, :]], axis=1)  # (T, N+1, d)
    a = adjacency[:n]
    return a.sum(axis=1)[None, :, None] * e[:, :n] - np.einsum("ij,tjd->tid", a, e)


def recorded(run: Run) -> np.ndarray:
    """(T,) bool: the ticks that hold every agent's telemetry (mode not -1); all of an engine's."""
    return np.all(run.safety.safety_mode != NO_SAMPLE, axis=1)


def summary(run: Run, tail: float = 0.1) -> dict[str, float]:
    """The metrics table row of one run (over its :func:`recorded` ticks when it lacks some)."""
    have = recorded(run)
    if not have.all() and have.any():
        run = dataclasses.replace(run, t=run.t[have], xi=run.xi[have], kp=run.kp[have], kv=run.kv[have])
    return {
        "duration_s": float(run.t[-1] - run.t[0]),
        "ultimate_bound_xi_m": ultimate_bound(run, tail),
        "settling_time_s": settling_time(run, tail),
        "peak_kp": float(np.nanmax(run.kp)),
        "peak_kv": float(np.nanmax(run.kv)),
        "final_kp_mean": float(np.nanmean(run.kp[-1])),
        "final_kv_mean": float(np.nanmean(run.kv[-1])),
        "kp_growth_per_s": growth_rate(run.t, run.kp),
        "kv_growth_per_s": growth_rate(run.t, run.kv),
        "max_xi_m": float(np.nanmax(xi_norm(run))),
        "diverged": bool(not np.all(np.isfinite(run.xi)) or np.nanmax(xi_norm(run)) > 1e6),
    }
