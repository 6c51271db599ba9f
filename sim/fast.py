"""The reference simulator's modes on the compiled kernels of :mod:`sim.kernel` (numba).

The same setup, run record and progress reports as :mod:`sim.refsim`'s numpy loops; the kernels
run the steps, a chunk of steps per call (one progress report per chunk).
"""

from __future__ import annotations

import msgspec
import numpy as np

from agent import laws
from leader import profile
from sim import kernel, lawkernels
from sim.setup import Progress, Setup, check_continuous
from tether import wire
from tether.runfile import Run, RunMeta

_FEED = {"measured": 0, "commanded": 1, "none": 2}


def _outputs(run: Run) -> tuple[np.ndarray, ...]:
    return run.p, run.v, run.a, run.u, run.xi, run.zeta, run.law_state, run.d


def layout(bound: laws.Bound, n: int, d: int) -> np.ndarray:
    """The law's initial state as the kernels take it: ``(S, d, N)``, axis first (``(1, d, N)`` of
    zeros for a law without state, so that the array has a shape numba can index)."""
    rows = bound.initial()
    if not rows:
        return np.zeros((1, d, n))
    return np.ascontiguousarray(np.stack([np.broadcast_to(np.asarray(r, dtype=float)[:, None], (d, n)) for r in rows]))


def _chunks(steps: int) -> list[tuple[int, int]]:
    """Ticks ``0 .. steps`` in about 100 calls (the progress reports of the numpy loop), of at least
    250 ticks (a call's own cost is tens of microseconds)."""
    every = max(250, steps // 100)
    return [(k, min(k + every, steps + 1)) for k in range(0, steps + 1, every)]


def discrete(s: Setup, steps: int, record: bool, progress: Progress | None, meta: RunMeta, threads: int = 1) -> Run:
    """:func:`sim.refsim.simulate`'s discrete mode, bit for bit. ``threads > 1`` splits each tick's agents
    into that many blocks computed on numba's threads (the same run bit for bit)."""
    m, topo, bound = s.mission, s.topo, s.bound
    n, d, h = m.n, m.dim, m.dt
    kern = lawkernels.kernel_of("sim.kernel", bound.law)
    ticks = np.arange(steps + 1)
    lp, lv, la = s.ref(ticks * h)
    lp, lv, la = (np.array(np.broadcast_to(x, (steps + 1, d)), dtype=float, order="C") for x in (lp, lv, la))
    # structure of arrays, axis first (see kernel.discrete)
    pos, vel, acc = np.zeros((2, d, n + 1)), np.zeros((2, d, n + 1)), np.zeros((2, d, n + 1))
    pos[0, :, :n], vel[0, :, :n] = s.p0.T, s.v0.T
    meas = np.zeros((d, n))
    state = layout(bound, n, d)
    coef = lawkernels.coefficients(bound, h)
    rows = steps + 1 if record else 1
    run = Run.empty(rows, m.agent_ids, d, meta, mode=wire.FLYING)  # no supervisor here
    kept = ticks if record else ticks[-1:]
    run.t[:] = kept * h
    run.leader_p[:], run.leader_v[:], run.leader_a[:] = lp[kept], lv[kept], la[kept]
    slot_w = np.ascontiguousarray(topo.slot_weight[:, :, 0])
    bank = tuple(np.ascontiguousarray(x.T) if isinstance(x, np.ndarray) and x.ndim == 2 else x
                 for x in s.dist.arrays())
    swd = np.ascontiguousarray(s.sum_wdelta.T)
    feed = _FEED[m.law.feedforward]
    u_omega, u_phase, inv = kernel.sine_pairs(bank[2], bank[3])
    blocks = max(1, min(threads, n))
    step = kern.discrete if blocks == 1 else kern.discrete_parallel
    for k0, k1 in _chunks(steps):
        step(k0, k1, steps, record, h, 0.5 * h * h, topo.kappa, topo.slot_src, slot_w, swd,
             feed, coef, lp, lv, la, pos, vel, acc, meas, state, *bank, *_outputs(run), u_omega, u_phase, inv, blocks)
        if progress is not None and k1 <= steps:
            progress(k0, steps)
    if progress is not None:
        progress(steps, steps)
    run.zero_absent_shown()  # the kernels record law_state alone
    return run


def continuous(s: Setup, steps: int, substeps: int, record: bool, progress: Progress | None, meta: RunMeta) -> Run:
    """:func:`sim.refsim.simulate`'s continuous mode, to round-off."""
    m, topo, bound = s.mission, s.topo, s.bound
    check_continuous(m)
    kern = lawkernels.kernel_of("sim.kernel", bound.law)
    n, d, h = m.n, m.dim, m.dt
    plan = kernel.solve_plan(n, topo.src, topo.dst, topo.weight, topo.kappa)
    perm = plan.perm  # the kernel numbers the agents in solving order: agent perm[q] at position q
    position = np.empty(n + 1, dtype=np.intp)
    position[perm], position[n] = np.arange(n), n

    def axis_first(x: np.ndarray) -> np.ndarray:  # (N, d) per agent -> (d, N) in solving order
        return np.ascontiguousarray(np.asarray(x, dtype=float)[perm].T)

    meta = msgspec.structs.replace(meta, substeps=substeps)
    # structure of arrays, axis first: the state [p, v, the law's] (column N the leader's, unused:
    # kernel.continuous)
    init = bound.initial()
    y = np.ones((2 + len(init), d, n + 1))
    y[0, :, :n], y[1, :, :n] = axis_first(s.p0), axis_first(s.v0)
    for row, x0 in enumerate(init):
        y[2 + row, :, :n] = axis_first(np.broadcast_to(x0, (n, d)))
    rows = steps + 1 if record else 1
    run = Run.empty(rows, m.agent_ids, d, meta, mode=wire.FLYING)  # no supervisor here
    ticks = np.arange(steps + 1)
    kept = ticks if record else ticks[-1:]
    run.t[:] = kept * h
    lead = s.ref(kept * h)
    run.leader_p[:], run.leader_v[:], run.leader_a[:] = (np.broadcast_to(x, (len(kept), d)) for x in lead)
    slot_src = np.ascontiguousarray(position[topo.slot_src[:, perm]])
    slot_w = np.ascontiguousarray(topo.slot_weight[:, perm, 0])
    kappa = np.ascontiguousarray(topo.kappa[perm])
    a_lead = np.zeros(n)  # a_i0, from the edge arrays (topo.adjacency is N^2)
    a_lead[topo.dst[topo.src == n]] = topo.weight[topo.src == n]
    a_lead = np.ascontiguousarray(a_lead[perm])
    bank = s.dist.arrays()

    def flat(x: np.ndarray) -> np.ndarray:  # (N, d) per agent -> (d (N+1),), the leader's elements zero
        out = np.zeros((d, n + 1))
        out[:, :n] = axis_first(x)
        return out.ravel()

    const, amp, omega, phase = (flat(x) for x in bank[:4])
    table, hold, has_random = np.ascontiguousarray(bank[4][perm]), np.ascontiguousarray(bank[5][perm]), bank[11]
    swd = flat(s.sum_wdelta)
    sin_m, cos_m = kernel.rotation_tables(omega, h, substeps)
    sines = kernel.sine_pairs(omega, phase)  # the leader's elements (0, 0): sin 0, amplitude 0
    state = y.reshape(len(y), d * (n + 1))  # a view: the kernel's flat layout
    # the exponential profile (Section 4's, a hold's) in closed form in the kernel; any other
    # evaluated here at every stage time
    ref = s.ref
    exp_lead = isinstance(ref, profile.ExpAccel)
    if isinstance(ref, profile.ExpAccel):
        lead0 = np.ascontiguousarray(np.stack([ref.p0, ref.v0, ref.a0]), dtype=float)
        decay = float(ref.decay)
        em, xm = kernel.exp_tables(decay, h, substeps)
        ref_p = ref_v = ref_a = np.zeros((d, 0))
    else:
        lead0, decay, (em, xm) = np.zeros((3, d)), 0.0, (np.zeros(0), np.zeros(0))
    for k0, k1 in _chunks(steps):
        if not exp_lead:
            times = kernel.stage_times(k0, k1, h, substeps)
            # axis first, (d, stages)
            ref_p, ref_v, ref_a = (np.ascontiguousarray(np.broadcast_to(x, (times.size, d)).T)
                                   for x in ref(times.ravel()))
        kern.continuous(k0, k1, steps, record, h, substeps, state, ref_p, ref_v, ref_a, exp_lead, lead0, decay,
                          em, xm, kappa,
                          slot_src, slot_w, swd, a_lead, *plan.kernel_args(), lawkernels.rates(bound), const, amp, *sines,
                          table, hold, has_random, sin_m, cos_m, *_outputs(run))
        if progress is not None and k1 <= steps:
            progress(k0, steps)
    if progress is not None:
        progress(steps, steps)
    run.zero_absent_shown()  # the kernels record law_state alone
    return run
