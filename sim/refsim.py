"""The reference simulator: the whole swarm in one process, vectorised over agents with numpy.

It is the oracle of the distributed runtime: with an ideal network, a lockstep run of the runtime
must reproduce the ``discrete`` mode to round-off. Its sampled-data semantics are the runtime's:

* Ticks ``t_k = k h``, ``h = 1 / rate``, ``k = 0 .. steps``.
* At ``t_k`` every vehicle is measured: ``p_i(t_k)``, ``v_i(t_k)`` and ``a_i(t_k)``, the mean
  acceleration over the previous period ``[t_{k-1}, t_k]`` (zero at k = 0, before any
  measurement). The leader's sample is its profile at ``t_k`` (position, velocity, acceleration).
* Agent i computes ``xi_i``, ``zeta_i`` (Eq. 8, 9) and ``u_i`` (Eq. 17) from its own sample and
  its in-neighbours' samples of the same tick, with the gains ``K(t_k)``; the feed-forward
  ``sum_j a_ij vdot_j`` uses the neighbours' measured accelerations ``a_j(t_k)``.
* ``u_i`` is held over ``[t_k, t_{k+1})`` (zero-order hold); the plant integrates exactly
  (:mod:`plant.double_integrator`, disturbance increments in closed form).
* The gains advance by the exact solution of their ODE with ``xi_i(t_k)``, ``zeta_i(t_k)`` held.

The ``continuous`` mode integrates the continuous-time closed loop with fixed-step RK4
(``substeps`` per control period) and exact neighbour accelerations: Eq. 17's feed-forward makes
``u`` depend on the neighbours' ``vdot``, an algebraic loop solved through ``L1``::

    L1 vdot = a_{i,N+1} a_ref + kappa * d - Kp * xi - Kv * zeta

Comparing the two modes shows what sampling changes.

Both modes have two engines: the numpy code below (the readable reference, vectorised over agents)
and the compiled kernels of :mod:`sim.kernel` (the ``[fast]`` extra, numba: one pass per agent per
step), equal to it bit for bit in the discrete mode and to round-off in the continuous one
(``tests/test_refsim.py``). ``engine="auto"`` takes the kernels when numba is installed and the
run has no ``on_tick`` (a live view paces the run sample by sample: the numpy loop serves it).
"""

from __future__ import annotations

import logging

import msgspec
import numpy as np

from leader import profile
from plant import double_integrator
from sim.setup import Engine, Mode, OnTick, Progress, Setup, check_continuous
from tether import graph, wire
from tether.mission import Mission
from tether.runfile import Run, RunMeta, Source

log = logging.getLogger("tether")

neighbour_sums = graph.neighbour_sums


def simulate(
    m: Mission,
    mode: Mode = "discrete",
    *,
    duration: float | None = None,
    record: bool = True,
    substeps: int = 10,
    progress: Progress | None = None,
    on_tick: OnTick | None = None,
    engine: Engine = "auto",
    threads: int = 1,
) -> Run:
    """Run a mission in one process, and say (a logged warning per agent, :func:`below_ground`)
    when a 3D run takes a vehicle below the ground, which this simulator does not have. ``duration`` overrides the mission's (a whole number of periods).

    Returns a :class:`~tether.runfile.Run` with one sample per control tick (``steps + 1``
    samples); with ``record=False`` only the final sample is kept (for benchmarks). ``on_tick`` is
    called after each recorded sample with the run and the sample's index (``--live``).
    ``engine``: ``"numpy"`` the reference code, ``"compiled"`` the kernels of :mod:`sim.kernel`
    (ValueError without numba), ``"auto"`` the kernels when they can run this mission.
    ``threads``: the compiled discrete mode splits each tick's agents over that many of numba's
    threads (``prange``; the same run bit for bit). Each tick ends on a barrier, so this pays only for
    large swarms on cores nobody else is using; the default is one.
    """
    run = _simulate(m, mode, duration, record, substeps, progress, on_tick, engine, threads)
    for aid, (t, z) in below_ground(m, run).items():
        log.warning("agent %d went below the ground (safety.ground = %g m) at t = %.2f s, down to z = %.3g m: the "
                    "reference simulator has no ground; `tether run` stops a flying vehicle on it", aid,
                    m.safety.ground, t, z)
    return run


def below_ground(m: Mission, run: Run) -> dict[int, tuple[float, float]]:
    """3D: the agents whose recorded height went below ``safety.ground``, each with the first such
    sample's time [s] and the lowest recorded height [m] (a run kept with ``record=False``: its
    last sample alone). 2D: none."""
    if m.dim < 3 or run.p.size == 0:
        return {}
    z = run.p[..., -1]  # (samples, agents)
    out: dict[int, tuple[float, float]] = {}
    for col, aid in enumerate(run.agent_ids):
        below = np.flatnonzero(z[:, col] < m.safety.ground)
        if below.size:
            out[int(aid)] = (float(run.t[below[0]]), float(np.nanmin(z[:, col])))
    return out


def _simulate(m: Mission, mode: Mode, duration: float | None, record: bool, substeps: int,
              progress: Progress | None, on_tick: OnTick | None, engine: Engine, threads: int) -> Run:
    s = Setup.of(m)
    steps = m.steps if duration is None else int(round(duration * m.rate))
    source: Source = "reference-discrete" if mode == "discrete" else "reference-continuous"
    meta = RunMeta(mission=m.name, source=source, law=s.bound.law.name, rate=m.rate, steps=steps,
                   seed=m.seed, law_state=s.bound.law.state, law_units=s.bound.units)
    if mode not in ("discrete", "continuous"):
        raise ValueError(f"mode must be 'discrete' or 'continuous', not {mode!r}")
    from sim import warm

    if takes_kernel(s, engine, on_tick) and (engine != "auto" or warm.compiled_or_background(s, mode, threads, steps)):
        from sim import fast
        try:
            warm.warm_refsim(s, mode, threads, meta)  # one compile per machine: blocks while another compiles
            if mode == "discrete":
                return fast.discrete(s, steps, record, progress, meta, threads)
            return fast.continuous(s, steps, substeps, record, progress, meta)
        except OSError as exc:
            # numba writes its compiled kernels to a cache on first use; a full or read-only disk
            # makes that write fail before any step ran. "auto" then takes the numpy path, which
            # gives the same numbers (tests/test_refsim_kernel.py); "compiled" was asked for: say why
            if engine == "compiled":
                raise
            log.warning("compiled kernels unavailable (%s: %s); running the numpy path", type(exc).__name__, exc)
            s = Setup.of(m)
    if mode == "discrete":
        return _discrete(s, steps, record, progress, meta, on_tick)
    return _continuous(s, steps, substeps, record, progress, meta, on_tick)


def takes_kernel(s: Setup, engine: Engine, on_tick: OnTick | None) -> bool:
    """Whether a run of ``s`` with ``engine`` takes the compiled kernels (``on_tick``: a live view,
    which only the numpy path serves); raises ``ValueError`` where ``engine="compiled"`` cannot run."""
    if engine == "numpy":
        return False
    from sim import kernel
    if engine == "compiled":
        if not kernel.AVAILABLE:
            raise ValueError("engine='compiled' needs numba (pip install 'tether[fast]')")
        if not kernel.supports(s.dist) or on_tick is not None:
            raise ValueError("engine='compiled' cannot run this mission (an unknown disturbance layout, or on_tick)")
        return True
    if engine != "auto":
        raise ValueError(f"engine must be 'auto', 'numpy' or 'compiled', not {engine!r}")
    return kernel.supports(s.dist) and on_tick is None


def _discrete(s: Setup, steps: int, record: bool, progress: Progress | None, meta: RunMeta,
              on_tick: OnTick | None = None) -> Run:
    m, topo, bound = s.mission, s.topo, s.bound
    n, d, h = m.n, m.dim, m.dt
    # full-shape kappa and weights: numpy is several times slower broadcasting (N, 1) over (N, d)
    kappa = np.repeat(topo.kappa[:, None], d, axis=1)
    weight = np.repeat(topo.slot_weight, d, axis=2)
    step = bound.law.step
    # the law's per-axis coefficients as (d,) arrays (they broadcast over the agents) and its state
    # as (N, d) arrays: its step then runs on every agent at once, element for element the agent's
    coef = tuple(np.array(col, dtype=float) for col in zip(*bound.coefficients(h)))
    state = tuple(np.array(np.broadcast_to(row, (n, d)), dtype=float) for row in bound.initial())
    lp, lv, la = s.ref(np.arange(steps + 1) * h)

    # one contiguous (N+1, d) array per quantity, agents first and the leader last: strided views
    # of a stacked array make every elementwise operation several times slower
    # acc: what each node shares for the feed-forward (measured, last command, or nothing)
    pos, vel, acc = np.zeros((n + 1, d)), np.zeros((n + 1, d)), np.zeros((n + 1, d))
    meas = np.zeros((n, d))
    feed = m.law.feedforward
    none = np.zeros((n, d))
    pos[:n], vel[:n] = s.p0, s.v0
    zero_d = s.dist.is_zero
    run = Run.empty(steps + 1 if record else 1, m.agent_ids, d, meta, mode=wire.FLYING)  # no supervisor here
    every = max(1, steps // 100)
    nsum = graph.neighbour_sums

    for k in range(steps + 1):
        pos[n], vel[n], acc[n] = lp[k], lv[k], la[k]
        p, v, a = pos[:n], vel[:n], meas
        sa = none if feed == "none" else nsum(topo, acc, weight)
        u, xi, zeta, nxt = step(kappa, p, v, nsum(topo, pos, weight), nsum(topo, vel, weight), sa, s.sum_wdelta,
                                state, coef)
        if record or k == steps:
            r = k if record else 0
            run.t[r] = k * h
            run.p[r], run.v[r], run.a[r], run.u[r] = p, v, a, u
            run.xi[r], run.zeta[r] = xi, zeta
            for row, x in zip(run.law_state, state):
                row[r] = x
            run.kp[r], run.kv[r] = bound.shown(state, 0.0)
            run.d[r] = 0.0 if zero_d else s.dist.value(k)
            run.leader_p[r], run.leader_v[r], run.leader_a[r] = lp[k], lv[k], la[k]
            if on_tick is not None:
                on_tick(run, r)
        if k == steps:
            break
        state = tuple(np.broadcast_to(x, (n, d)) for x in nxt)
        dv, dp = s.dist.increments(k)
        pos[:n], vel[:n], meas = double_integrator.step(p, v, u, dv, dp, h)
        acc[:n] = u if feed == "commanded" else meas
        if progress is not None and k % every == 0:
            progress(k, steps)
    if progress is not None:
        progress(steps, steps)
    return run


def _continuous(s: Setup, steps: int, substeps: int, record: bool, progress: Progress | None, meta: RunMeta,
                on_tick: OnTick | None = None) -> Run:
    m, topo, bound = s.mission, s.topo, s.bound
    check_continuous(m)
    rate = getattr(bound.law, "rate")
    rcoef = tuple(np.array(col, dtype=float) for col in zip(*bound.rates()))
    n, d, h = m.n, m.dim, m.dt
    hf = h / substeps
    kappa = topo.kappa[:, None]
    a_lead = topo.adjacency[:n, n][:, None]
    l1, _ = graph.partition(topo.adjacency)
    l1_inv = np.linalg.inv(l1)
    meta = msgspec.structs.replace(meta, substeps=substeps)

    def rhs(t: float, y: np.ndarray) -> tuple[np.ndarray, dict]:
        p, v, *x = y
        lp, lv, la = s.ref(t)
        xp = np.vstack([p, lp])
        xv = np.vstack([v, lv])
        sp = neighbour_sums(topo, xp)
        sv = neighbour_sums(topo, xv)
        dist = s.dist.value_at(t)
        row, xi, zeta, rates = rate(kappa, p, v, sp, sv, s.sum_wdelta, a_lead * la + kappa * dist, tuple(x), rcoef)
        vdot = l1_inv @ row
        dy = np.stack([v, vdot, *rates])
        return dy, {"xi": xi, "zeta": zeta, "vdot": vdot, "d": dist, "lead": (lp, lv, la)}

    y = np.stack([s.p0, s.v0, *(np.broadcast_to(row, (n, d)) for row in bound.initial())]).astype(float)
    run = Run.empty(steps + 1 if record else 1, m.agent_ids, d, meta, mode=wire.FLYING)  # no supervisor here
    every = max(1, steps // 100)
    for k in range(steps + 1):
        t = k * h
        k1, aux = rhs(t, y)
        if record or k == steps:
            r = k if record else 0
            run.t[r] = t
            run.p[r], run.v[r], run.a[r] = y[0], y[1], aux["vdot"]
            run.u[r] = aux["vdot"] - aux["d"]
            run.xi[r], run.zeta[r] = aux["xi"], aux["zeta"]
            run.law_state[:, r] = y[2:]
            run.kp[r], run.kv[r] = bound.shown(y[2:], 0.0)
            run.d[r] = aux["d"]
            run.leader_p[r], run.leader_v[r], run.leader_a[r] = aux["lead"]
            if on_tick is not None:
                on_tick(run, r)
        if k == steps:
            break
        for j in range(substeps):
            ts = t + j * hf
            if j:
                k1, _ = rhs(ts, y)
            k2, _ = rhs(ts + 0.5 * hf, y + 0.5 * hf * k1)
            k3, _ = rhs(ts + 0.5 * hf, y + 0.5 * hf * k2)
            k4, _ = rhs(ts + hf, y + hf * k3)
            y = y + (hf / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        if progress is not None and k % every == 0:
            progress(k, steps)
    if progress is not None:
        progress(steps, steps)
    return run

