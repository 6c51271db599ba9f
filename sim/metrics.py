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

:func:`report` is the ``metrics.json`` of a run (``tether simulate``, ``tether run``, ``tether report``):
:func:`summary` (the agents' own ``xi``) beside the true formation error and the tracking error, each
named for what it is, when the run holds its mission (:func:`geometry`).

A recorder's run may lack ticks (a run stopped early, a recorder frozen or killed: their modes read
-1). :func:`summary` is taken over the ticks that hold every agent's telemetry (:func:`recorded`):
a missing sample is not a divergence, and the tail and final values are those of the last ticks
recorded. The engines' runs hold every tick, so for them nothing changes.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

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
    # a vehicle with no position (killed, cut off) leaves only the agents that hear it undefined
    missing = ~np.all(np.isfinite(e), axis=2)  # (T, N+1)
    xi = a.sum(axis=1)[None, :, None] * e[:, :n] - np.einsum("ij,tjd->tid", a, np.where(missing[..., None], 0.0, e))
    undefined = missing[:, :n] | (missing.astype(float) @ (a > 0).T.astype(float) > 0)
    xi[undefined] = np.nan
    return xi


POSITIONING = 0.1
"""The band [m] of :func:`report`'s ``formation_settling_time_s``: the paper's positioning accuracy."""


DENSE_AGENTS = 2000
"""The true errors use the graph's dense ``(N+1, N+1)`` adjacency: above this many agents (32 MB of
it) :func:`geometry` gives none, and the metrics hold the agents' own errors only."""


@dataclasses.dataclass(frozen=True)
class Geometry:
    """What the true errors need of a mission, in the run's agent order."""

    adjacency: np.ndarray
    """``(N+1, N+1)`` weights ``a_ij`` (i hears j), the leader last."""
    offsets: np.ndarray
    """``(N, d)`` formation offsets ``h_i`` [m]."""


def geometry(run: Run) -> Geometry | None:
    """The run's :class:`Geometry` from the mission text it holds; None when it holds none, one of
    more than :data:`DENSE_AGENTS` agents, or one whose agents are not the run's (parsing only: no
    file is read)."""
    from tether import graph
    from tether import mission as ms

    if not run.meta.mission_text:
        return None
    try:
        m = ms.loads(run.meta.mission_text)
    except ms.SchemaError:
        return None
    ids = [a.id for a in m.agents]
    if sorted(ids) != sorted(int(a) for a in run.agent_ids) or m.dim != run.p.shape[2]:
        return None
    if len(ids) > DENSE_AGENTS:
        return None
    order = [ids.index(int(a)) for a in run.agent_ids] + [len(ids)]
    adjacency = np.asarray(graph.topology(m).adjacency, dtype=float)[np.ix_(order, order)]
    offsets = np.array([m.agents[k].offset for k in order[:-1]], dtype=float)
    return Geometry(adjacency, offsets)


def true_xi_norm(run: Run, g: Geometry) -> np.ndarray:
    """``(T, N)`` norm of the true formation error (Eq. 8 from the vehicles' positions) [m]."""
    return np.linalg.norm(formation_error(run, g.adjacency, g.offsets), axis=2)


def tracking_norm(run: Run, g: Geometry) -> np.ndarray:
    """``(T, N)`` distance of each vehicle from its slot ``p_leader + h_i`` [m]."""
    return np.linalg.norm(run.p - g.offsets[None] - run.leader_p[:, None, :], axis=2)


def settled_within(t: np.ndarray, worst: np.ndarray, band: float) -> float:
    """The first sample time from which ``worst`` stays at or below ``band`` to the end (NaN if its
    last sample is above it)."""
    above = np.nonzero(~(worst <= band))[0]
    if len(above) == 0:
        return float(t[0])
    last = above[-1]
    return float(t[last + 1]) if last + 1 < len(t) else math.nan


def report(run: Run, tail: float = 0.1) -> dict[str, float | bool]:
    """``metrics.json``: :func:`summary` (its ``xi`` is the agents' own, from the data they had) with
    ``settle_band_m``, the band its ``settling_time_s`` is measured against, and where the run holds
    its mission (:func:`geometry`) the true formation error (Eq. 8 from the positions), the tracking
    error and the time the true error settles within :data:`POSITIONING`."""
    out: dict[str, float | bool] = dict(summary(run, tail))
    out["settle_band_m"] = 1.1 * out["ultimate_bound_xi_m"]
    g = geometry(run)
    if g is None:
        return out
    # over every tick: a vehicle that stopped reporting leaves its own columns empty, not the others'
    sl = tail_slice(run, tail)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN ticks (a recorder's gaps) stay NaN
        return {**out, **_truth(run, g, sl)}


def _truth(run: Run, g: Geometry, sl: slice) -> dict[str, float | bool]:
    true, track = true_xi_norm(run, g), tracking_norm(run, g)
    worst = np.nanmax(true, axis=1)
    rows = np.isfinite(run.t) & np.isfinite(worst)  # ticks with no error at all (gaps) judge nothing
    return {"formation_error_bound_m": float(np.nanmax(true[sl])),
            "formation_error_max_m": float(np.nanmax(true)),
            "tracking_error_m": float(np.nanmax(track[sl])),
            "tracking_error_max_m": float(np.nanmax(track)),
            "formation_settling_time_s": settled_within(run.t[rows], worst[rows], POSITIONING) if rows.any()
            else math.nan}


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
