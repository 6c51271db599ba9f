"""The reference simulator's compiled kernels (numba, the ``[fast]`` extra): one pass per agent per step.

:mod:`sim.refsim` keeps its numpy form as the readable reference; these kernels compute the same
arithmetic, operation for operation, agent by agent, without a numpy temporary per operation:

* :func:`discrete` is the discrete mode's loop (the law, the exact gain update, the exact
  zero-order-hold double integrator, the disturbance increments of
  :meth:`plant.disturbance.DisturbanceBank.increments` and values of ``value``), each product and
  sum in the numpy path's order, so that its runs equal the numpy path's bit for bit
  (``tests/test_refsim.py``). Positions, velocities and shared accelerations are double-buffered
  (``[k % 2]`` is tick k's), so one pass over the agents reads tick k and writes tick k+1. The
  arrays are laid out axis first and every loop stores into one array over a block of agents, so
  that LLVM vectorises it across agents; each distinct ``(omega, phase)`` pair's sine and cosine is
  computed once per tick (:func:`sine_pairs`). :func:`discrete_parallel` runs blocks of agents on
  numba's threads.
* :func:`continuous` is the continuous mode's RK4, every stage in one function body, one axis
  after the other (the law's gains are per axis and ``L1`` acts on each axis alone); the leader's
  profile is evaluated by numpy beforehand at every stage time (:func:`stage_times`), or in the
  kernel in closed form for the exponential profile (Section 4's and a hold's). The algebraic
  loop ``L1 a = b`` is solved block by block over the graph's strongly connected components
  (:class:`SolvePlan`; the whole ``L1^{-1}`` for a few agents, forward substitution when no agent
  is on a cycle), the sinusoids are rotated from their phase at each control tick by the
  angle-addition formula (two sines a control step per axis instead of forty) and the stages at
  one time share theirs: it equals the numpy path to round-off, not bit for bit.

The disturbance bank is read from its arrays (:meth:`~plant.disturbance.DisturbanceBank.arrays`); a
bank of another layout (``layout_known`` False) makes :func:`supports` say no, and the simulator
keeps its numpy path, which goes through the bank's own methods.

The law is the mission's :class:`agent.laws.FormationLaw`, called through ``law_step`` and
``law_rate`` (:mod:`sim.lawkernels` compiles a copy of this module for a law other than Eq. 17's).

Without numba installed, :data:`AVAILABLE` is False and nothing here is compiled.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import numpy as np

from agent.laws import sigma
from plant.disturbance import DisturbanceBank
from tether import graph

numba: Any
try:  # the [fast] extra
    import numba
except ImportError:  # exercised where numba is missing (tests/test_refsim_kernel.py hides it)
    numba = None

AVAILABLE = numba is not None
"""Whether the compiled kernels can run here (numba imports)."""

def supports(dist: DisturbanceBank) -> bool:
    """Whether the kernels evaluate ``dist`` exactly as its own methods do (its layout is known)."""
    return (AVAILABLE and dist.layout_known
            # one layer of each model: a summed disturbance of several sinusoids or random terms
            # ((L, n, d) and (R, n, M, d) arrays) is evaluated by the numpy path
            and dist.amp.ndim == 2 and dist.table.ndim == 3 and dist.hold_ticks.ndim == 1)


if AVAILABLE:  # a kernel's cache goes stale with the functions it calls too (sim/jitcache.py)
    from sim import jitcache

    jitcache.install()


def _jit(fn: Callable[..., Any]) -> Callable[..., Any]:
    # no fastmath: no reassociation, no fused multiply-adds, so each operation rounds as numpy's does
    return fn if numba is None else numba.njit(cache=True, nogil=True)(fn)


jit = _jit
"""Compile ``fn`` as every kernel of this package is compiled (cached, no GIL, no fast-math); ``fn``
itself without numba."""

# The law the kernels run (sim.lawkernels rebinds these six names in a copy of this module for
# another law): Eq. 17's step and continuous-time form, and its two state variables moved between
# the (S, j, k) state arrays and the step's tuples.
law_step = _jit(sigma.step)
law_rate = _jit(sigma.rate)


@_jit
def law_load(a: np.ndarray, j: int, k: int) -> tuple[float, float]:
    return (a[0, j, k], a[1, j, k])


@_jit
def law_store(a: np.ndarray, j: int, k: int, x: tuple[float, float]) -> None:
    a[0, j, k] = x[0]
    a[1, j, k] = x[1]


@_jit
def law_shown(x: tuple[float, float]) -> tuple[float, float]:
    return (x[0], x[1])


@_jit
def law_record(out: np.ndarray, r: int, i: int, c: int, x: tuple[float, float]) -> None:
    """Agent ``i``'s state ``x`` on axis ``c`` into row ``r`` of ``out`` ``(S, T, N, d)`` (``Run.law_state``)."""
    out[0, r, i, c] = x[0]
    out[1, r, i, c] = x[1]


@_jit
def _random(table: np.ndarray, hold: np.ndarray, i: int, k: int, c: int) -> float:
    idx = k // hold[i]
    last = table.shape[1] - 1
    return table[i, idx if idx < last else last, c]


def _jit_parallel(fn: Callable[..., Any]) -> Callable[..., Any]:
    return fn if numba is None else numba.njit(cache=True, nogil=True, parallel=True)(fn)


@_jit
def _sines(k: int, lo: int, hi: int, steps: int, record: bool, h: float, has_sine: bool, zero_d: bool,
           u_omega: np.ndarray, u_phase: np.ndarray, snu: np.ndarray, csu: np.ndarray) -> None:
    """``sin`` and ``cos`` of ``omega (k h) + phase`` for the distinct pairs ``lo .. hi-1`` (see
    :func:`sine_pairs`): the very operations of ``DisturbanceBank``, once per pair and not once per
    agent and axis that has it (the same inputs give the same bits)."""
    last = k == steps
    tk = k * h
    if has_sine and not last:
        # sine and cosine of one argument in one loop body: LLVM calls libm's sincos once for the
        # pair, in about two thirds of the two calls' time; glibc's sincos shares sin's and cos's
        # code and gives their bits (tests/test_refsim_kernel.py checks this libm's, at every scale)
        for u in range(lo, hi):
            x = u_omega[u] * tk + u_phase[u]
            snu[u] = math.sin(x)
            csu[u] = math.cos(x)
    elif has_sine or ((record or last) and not zero_d):
        for u in range(lo, hi):
            snu[u] = math.sin(u_omega[u] * tk + u_phase[u])


def sine_pairs(omega: np.ndarray, phase: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct ``(omega, phase)`` pairs of ``(d, n)`` arrays, told apart by their bits (``-0.0``
    is not ``0.0`` here), and each element's pair: ``u_omega, u_phase`` ``(U,)``, ``inv`` ``(d, n)``."""
    bits = np.stack([omega.ravel(), phase.ravel()], axis=1).view(np.int64)
    _, first, inv = np.unique(bits, axis=0, return_index=True, return_inverse=True)
    return (np.ascontiguousarray(omega.ravel()[first]), np.ascontiguousarray(phase.ravel()[first]),
            np.ascontiguousarray(inv.reshape(omega.shape), dtype=np.intp))


@_jit
def _block(k: int, lo: int, hi: int, steps: int, record: bool, h: float, hh2: float,
           kappa: np.ndarray, slot_src: np.ndarray, slot_w: np.ndarray, swd: np.ndarray,
           feed: int, coef: np.ndarray,
           pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, meas: np.ndarray, state: np.ndarray,
           const: np.ndarray, amp: np.ndarray, omega: np.ndarray, phase: np.ndarray, table: np.ndarray,
           hold: np.ndarray, cv_s: np.ndarray, cv_c: np.ndarray, cp_s: np.ndarray, cp_c: np.ndarray,
           has_sine: bool, has_random: bool, has_const: bool,
           out_p: np.ndarray, out_v: np.ndarray, out_a: np.ndarray, out_u: np.ndarray, out_xi: np.ndarray,
           out_zeta: np.ndarray, out_x: np.ndarray, out_d: np.ndarray,
           sp: np.ndarray, sv: np.ndarray, sa: np.ndarray, dvb: np.ndarray, dpb: np.ndarray,
           snb: np.ndarray, csb: np.ndarray, inv: np.ndarray, snu: np.ndarray, csu: np.ndarray,
           own: bool = False) -> None:
    """Tick k of agents ``lo .. hi-1``, axis by axis: the neighbour sums slot by slot (as
    :func:`tether.graph.neighbour_sums`), the disturbance increments, then the law's step and
    the plant element-wise. Reads tick k's half of the double buffers, writes tick k+1's half and
    the rows ``lo .. hi`` of everything else: blocks of agents can run at the same time. The sines
    are those of :func:`_sines` (``snu, csu``), or with ``own`` computed here for these agents
    alone, from the same inputs (the same bits; for blocks on threads when few agents share one)."""
    d = meas.shape[0]
    slots = slot_src.shape[0]
    cur = k & 1
    nxt = cur ^ 1
    keep = record or k == steps
    r = k if record else 0
    last = k == steps
    zero_d = not (has_sine or has_random or has_const)
    # every loop below runs over a zero-based view of rows lo .. hi and stores into one array:
    # LLVM then vectorises it across agents (its aliasing checks stay few, no negative-index fix-up)
    m = hi - lo
    ka = kappa[lo:hi]
    xs = sp[lo:hi]
    zs = sv[lo:hi]
    us = sa[lo:hi]
    dvs = dvb[lo:hi]
    dps = dpb[lo:hi]
    sns = snb[lo:hi]
    css = csb[lo:hi]
    for c in range(d):
        pc = pos[cur, c]
        vc = vel[cur, c]
        ac = acc[cur, c]
        for s in range(slots):
            src = slot_src[s, lo:hi]
            ws = slot_w[s, lo:hi]
            if s == 0:
                for i in range(m):
                    xs[i] = ws[i] * pc[src[i]]
                for i in range(m):
                    zs[i] = ws[i] * vc[src[i]]
                if feed != 2:
                    for i in range(m):
                        us[i] = ws[i] * ac[src[i]]
            else:
                for i in range(m):
                    xs[i] += ws[i] * pc[src[i]]
                for i in range(m):
                    zs[i] += ws[i] * vc[src[i]]
                if feed != 2:
                    for i in range(m):
                        us[i] += ws[i] * ac[src[i]]
        # DisturbanceBank.increments(k), term by term (and the sines again for value(k)), each
        # sine and cosine that of the agent's own (omega, phase), computed once by _sines
        if own:  # these agents' own (omega, phase), as _sines takes the distinct pairs
            _sines(k, 0, m, steps, record, h, has_sine, zero_d, omega[c, lo:hi], phase[c, lo:hi], sns, css)
        elif has_sine or (keep and not zero_d):
            iv = inv[c, lo:hi]
            for i in range(m):
                sns[i] = snu[iv[i]]
            if has_sine and not last:
                for i in range(m):
                    css[i] = csu[iv[i]]
        if not last:
            if has_random or has_const:
                cn = const[c, lo:hi]
                for i in range(m):
                    dps[i] = cn[i] + (_random(table, hold, lo + i, k, c) if has_random else 0.0)  # held
                for i in range(m):
                    dvs[i] = dps[i] * h
                for i in range(m):
                    dps[i] = dps[i] * hh2
                if has_sine:
                    # the held terms plus the sinusoids' increments, summed first: the bank's order
                    a1 = cv_s[c, lo:hi]
                    a2 = cv_c[c, lo:hi]
                    for i in range(m):
                        dvs[i] = dvs[i] + (sns[i] * a1[i] + css[i] * a2[i])
                    a1 = cp_s[c, lo:hi]
                    a2 = cp_c[c, lo:hi]
                    for i in range(m):
                        dps[i] = dps[i] + (sns[i] * a1[i] + css[i] * a2[i])
            elif has_sine:
                a1 = cv_s[c, lo:hi]
                a2 = cv_c[c, lo:hi]
                for i in range(m):
                    dvs[i] = sns[i] * a1[i] + css[i] * a2[i]
                a1 = cp_s[c, lo:hi]
                a2 = cp_c[c, lo:hi]
                for i in range(m):
                    dps[i] = sns[i] * a1[i] + css[i] * a2[i]
            else:
                for i in range(m):
                    dvs[i] = 0.0
                for i in range(m):
                    dps[i] = 0.0
        p = pc[lo:hi]
        v = vc[lo:hi]
        sw = swd[c, lo:hi]
        # the law's step (law_step), element-wise: xi into xs, zeta into zs, u into us; the state
        # recorded as it was at tick k, then advanced in place
        cf = coef[c]
        if feed == 2:
            for i in range(m):
                us[i] = 0.0
        for i in range(m):
            q = lo + i
            x = law_load(state, c, q)
            u_, e_, z_, xn = law_step(ka[i], p[i], v[i], xs[i], zs[i], us[i], sw[i], x, cf)
            xs[i] = e_
            zs[i] = z_
            us[i] = u_
            if keep:
                law_record(out_x, r, q, c, x)
            if not last:
                law_store(state, c, q, xn)
        if keep:
            mc = meas[c, lo:hi]
            for i in range(m):
                q = lo + i
                out_p[r, q, c] = p[i]
                out_v[r, q, c] = v[i]
                out_a[r, q, c] = mc[i]
                out_u[r, q, c] = us[i]
                out_xi[r, q, c] = xs[i]
                out_zeta[r, q, c] = zs[i]
                if zero_d:
                    out_d[r, q, c] = 0.0
                else:
                    out_d[r, q, c] = (const[c, q] + amp[c, q] * sns[i]
                                      + (_random(table, hold, q, k, c) if has_random else 0.0))
        if last:
            continue
        # plant.double_integrator.step
        pn = pos[nxt, c, lo:hi]
        vn = vel[nxt, c, lo:hi]
        an = acc[nxt, c, lo:hi]
        mc = meas[c, lo:hi]
        for i in range(m):
            pn[i] = p[i] + h * v[i] + hh2 * us[i] + dps[i]
        for i in range(m):
            vn[i] = v[i] + h * us[i] + dvs[i]
        for i in range(m):
            mc[i] = us[i] + dvs[i] / h
        if feed == 1:
            for i in range(m):
                an[i] = us[i]
        else:
            for i in range(m):
                an[i] = mc[i]


@_jit
def discrete(k0: int, k1: int, steps: int, record: bool, h: float, hh2: float,
             kappa: np.ndarray, slot_src: np.ndarray, slot_w: np.ndarray, swd: np.ndarray,
             feed: int, coef: np.ndarray,
             lp: np.ndarray, lv: np.ndarray, la: np.ndarray,
             pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, meas: np.ndarray, state: np.ndarray,
             const: np.ndarray, amp: np.ndarray, omega: np.ndarray, phase: np.ndarray, table: np.ndarray,
             hold: np.ndarray, cv_s: np.ndarray, cv_c: np.ndarray, cp_s: np.ndarray, cp_c: np.ndarray,
             has_sine: bool, has_random: bool, has_const: bool,
             out_p: np.ndarray, out_v: np.ndarray, out_a: np.ndarray, out_u: np.ndarray, out_xi: np.ndarray,
             out_zeta: np.ndarray, out_x: np.ndarray, out_d: np.ndarray,
             u_omega: np.ndarray, u_phase: np.ndarray, inv: np.ndarray, blocks: int) -> None:
    """Ticks ``k0 .. k1-1`` of the discrete mode (``feed``: 0 measured, 1 commanded, 2 none), on
    one thread (``blocks`` is :func:`discrete_parallel`'s, unused here).

    Structure of arrays, axis first: ``pos, vel, acc`` ``(2, d, N+1)`` (double-buffered: ``[k % 2]``
    is tick k's; column N the leader), ``meas`` ``(d, N)``, ``state`` ``(S, d, N)`` (the law's; ``coef`` ``(d, C)``
    its coefficients, row c axis c's), the
    bank's ``(n, d)`` arrays transposed to ``(d, n)``. Samples go to row k of ``out_*`` ``(T, N, d)``
    (``record``) or row 0 at ``k == steps``."""
    d, n = meas.shape
    buf = np.empty((7, n))
    sp, sv, sa, dvb, dpb, snb, csb = buf[0], buf[1], buf[2], buf[3], buf[4], buf[5], buf[6]
    pairs = u_omega.shape[0]
    snu = np.empty(pairs)
    csu = np.empty(pairs)
    zero_d = not (has_sine or has_random or has_const)
    for k in range(k0, k1):
        cur = k & 1
        for c in range(d):
            pos[cur, c, n] = lp[k, c]
            vel[cur, c, n] = lv[k, c]
            acc[cur, c, n] = la[k, c]
        _sines(k, 0, pairs, steps, record, h, has_sine, zero_d, u_omega, u_phase, snu, csu)
        _block(k, 0, n, steps, record, h, hh2, kappa, slot_src, slot_w, swd, feed, coef,
               pos, vel, acc, meas, state, const, amp, omega, phase, table, hold, cv_s, cv_c, cp_s, cp_c,
               has_sine, has_random, has_const, out_p, out_v, out_a, out_u, out_xi, out_zeta, out_x,
               out_d, sp, sv, sa, dvb, dpb, snb, csb, inv, snu, csu)


@_jit_parallel
def discrete_parallel(k0: int, k1: int, steps: int, record: bool, h: float, hh2: float,
                      kappa: np.ndarray, slot_src: np.ndarray, slot_w: np.ndarray, swd: np.ndarray,
                      feed: int, coef: np.ndarray,
                      lp: np.ndarray, lv: np.ndarray, la: np.ndarray,
                      pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, meas: np.ndarray, state: np.ndarray,
                      const: np.ndarray, amp: np.ndarray, omega: np.ndarray, phase: np.ndarray, table: np.ndarray,
                      hold: np.ndarray, cv_s: np.ndarray, cv_c: np.ndarray, cp_s: np.ndarray, cp_c: np.ndarray,
                      has_sine: bool, has_random: bool, has_const: bool,
                      out_p: np.ndarray, out_v: np.ndarray, out_a: np.ndarray, out_u: np.ndarray,
                      out_xi: np.ndarray, out_zeta: np.ndarray, out_x: np.ndarray,
                      out_d: np.ndarray, u_omega: np.ndarray, u_phase: np.ndarray, inv: np.ndarray,
                      blocks: int) -> None:
    """:func:`discrete` with each tick's agents split into ``blocks`` runs of agents (multiples of
    8) computed on numba's threads (``prange``); an agent's arithmetic does not depend on the
    split, so the run is the same bit for bit."""
    d, n = meas.shape
    buf = np.empty((7, n))
    sp, sv, sa, dvb, dpb, snb, csb = buf[0], buf[1], buf[2], buf[3], buf[4], buf[5], buf[6]
    pairs = u_omega.shape[0]
    snu = np.empty(pairs)
    csu = np.empty(pairs)
    zero_d = not (has_sine or has_random or has_const)
    size = ((n + blocks - 1) // blocks + 7) // 8 * 8
    # most agents with sines of their own: each block takes its agents' sines itself (one parallel
    # region a tick, where a shared pass first was two); else the distinct ones first, once
    own = 2 * pairs > n * d
    for k in range(k0, k1):
        cur = k & 1
        for c in range(d):
            pos[cur, c, n] = lp[k, c]
            vel[cur, c, n] = lv[k, c]
            acc[cur, c, n] = la[k, c]
        if not own:
            _sines(k, 0, pairs, steps, record, h, has_sine, zero_d, u_omega, u_phase, snu, csu)
        for b in numba.prange(blocks):
            lo = min(b * size, n)
            hi = min(lo + size, n)
            _block(k, lo, hi, steps, record, h, hh2, kappa, slot_src, slot_w, swd, feed, coef,
                   pos, vel, acc, meas, state, const, amp, omega, phase, table, hold, cv_s, cv_c, cp_s, cp_c,
                   has_sine, has_random, has_const, out_p, out_v, out_a, out_u, out_xi, out_zeta, out_x,
                   out_d, sp, sv, sa, dvb, dpb, snb, csb, inv, snu, csu, own)


def stage_times(k0: int, k1: int, h: float, substeps: int) -> np.ndarray:
    """The times at which the continuous mode evaluates its right-hand side over control steps
    ``k0 .. k1-1``, ``(k1 - k0, substeps, 3)``: ``ts``, ``ts + hf/2``, ``ts + hf`` with
    ``ts = k h + j hf``, computed as the numpy path computes them."""
    hf = h / substeps
    t = np.arange(k0, k1)[:, None] * h
    ts = t + np.arange(substeps)[None, :] * hf
    return np.stack([ts, ts + 0.5 * hf, ts + hf], axis=2)


@_jit
def _stage_time(t: float, j: int, at: int, hf: float) -> float:
    """The time of substep ``j``'s stage ``at`` (0: its start, 1: its middle, 2: its end) from the
    control tick's ``t``, as :func:`stage_times` computes it."""
    ts = t + j * hf
    return ts if at == 0 else (ts + 0.5 * hf if at == 1 else ts + hf)


def _jit_numpy_errors(fn: Callable[..., Any]) -> Callable[..., Any]:
    # the continuous kernel divides only by kappa_i > 0 (tether.graph.topology checks it): numpy's
    # error model drops the zero-division test, which otherwise slows the small loops around it
    return fn if numba is None else numba.njit(cache=True, nogil=True, error_model="numpy")(fn)


DENSE_SOLVE = 32
"""Up to this many agents :func:`continuous` applies the whole ``L1^{-1}`` (N^2 products, in loops
that stay small); beyond, block by block (see :func:`solve_plan`)."""

DENSE_MAX = graph.DENSE_MAX
"""The largest strongly connected block (and the largest N with one block holding more than half
the agents, which :func:`solve_plan` then solves whole) whose inverse is formed: ``N^2`` doubles."""


def largest_block(n: int, src: np.ndarray, dst: np.ndarray) -> int:
    """The size of the largest strongly connected block among the agents (:func:`strong_blocks`)."""
    return max(len(b) for b in strong_blocks(n, src, dst))


@dataclasses.dataclass(frozen=True)
class SolvePlan:
    """How :func:`continuous` solves ``L1 a = b`` (``L1 = diag(kappa) - A`` among the agents).

    The agents are renumbered in solving order (``perm[q]`` is the agent at position q): the
    strongly connected components of their graph, each component after every component it hears.
    Agent i's row is ``kappa_i a_i - sum_j a_ij a_j = b_i``: the sum over earlier blocks is added to
    ``b_i``, then the block's own small system is solved with its inverse (``1 / kappa_i`` for an
    agent alone in its block, as on a tree or a chain). O(N + edges + sum of block sizes squared)
    per solve, where ``L1^{-1} b`` is O(N^2). With few agents (:data:`DENSE_SOLVE`) or one block
    holding more than half of them, ``dense``: a single block, the whole inverse.

    Positions are ``q``: block b is ``block_ptr[b] .. block_ptr[b + 1] - 1``; the in-edges from
    earlier blocks of position q are ``ext_src[ext_ptr[q]:ext_ptr[q + 1]]`` (positions) with
    weights ``ext_w``; block b's inverse is row-major at ``inv[inv_ptr[b]:]`` (empty for a
    singleton)."""

    perm: np.ndarray
    dense: bool
    block_ptr: np.ndarray
    ext_ptr: np.ndarray
    ext_src: np.ndarray
    ext_w: np.ndarray
    inv_ptr: np.ndarray
    inv: np.ndarray

    def kernel_args(self) -> tuple[Any, ...]:
        return (self.perm, self.dense, self.block_ptr, self.ext_ptr, self.ext_src, self.ext_w, self.inv_ptr,
                self.inv)


def strong_blocks(n: int, src: np.ndarray, dst: np.ndarray) -> list[list[int]]:
    """The strongly connected components of the agents' graph (edges ``src -> dst``; node ``n``, the
    leader, left out), each after every component it has an in-edge from (Tarjan's algorithm,
    iterative, walking from an agent to its in-neighbours)."""
    ins: list[list[int]] = [[] for _ in range(n)]
    for s_, d_ in zip(src.tolist(), dst.tolist()):
        if s_ < n:
            ins[d_].append(s_)
    index = [-1] * n
    low = [0] * n
    on_stack = [False] * n
    stack: list[int] = []
    blocks: list[list[int]] = []
    counter = 0
    for root in range(n):
        if index[root] >= 0:
            continue
        work = [(root, 0)]
        while work:
            v, pos = work[-1]
            if pos == 0:
                index[v] = low[v] = counter
                counter += 1
                stack.append(v)
                on_stack[v] = True
            if pos < len(ins[v]):
                work[-1] = (v, pos + 1)
                w = ins[v][pos]
                if index[w] < 0:
                    work.append((w, 0))
                elif on_stack[w]:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                u = work[-1][0]
                low[u] = min(low[u], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack[w] = False
                    comp.append(w)
                    if w == v:
                        break
                blocks.append(sorted(comp))
    return blocks


def solve_plan(n: int, src: np.ndarray, dst: np.ndarray, weight: np.ndarray, kappa: np.ndarray) -> SolvePlan:
    """The :class:`SolvePlan` of a mission's graph (``src, dst, weight`` its edges, node ``n`` the
    leader, whose edges are not in ``L1``; ``kappa`` the in-degrees)."""
    blocks = strong_blocks(n, src, dst)
    perm = np.array([i for b in blocks for i in b], dtype=np.intp)
    dense = n <= DENSE_SOLVE or (max(len(b) for b in blocks) * 2 > n and n <= DENSE_MAX)
    if dense:
        blocks = [perm.tolist()]
    position = np.empty(n, dtype=np.intp)
    position[perm] = np.arange(n)
    block_of = np.empty(n, dtype=np.intp)
    block_ptr = np.zeros(len(blocks) + 1, dtype=np.intp)
    for b, comp in enumerate(blocks):
        block_of[position[comp]] = b
        block_ptr[b + 1] = block_ptr[b] + len(comp)
    ext: list[list[tuple[int, float]]] = [[] for _ in range(n)]
    mats = [np.diag(kappa[comp].astype(float)) for comp in blocks]
    for s_, d_, w_ in zip(src.tolist(), dst.tolist(), weight.tolist()):
        if s_ >= n:
            continue
        qs, qd = int(position[s_]), int(position[d_])
        b = int(block_of[qd])
        if block_of[qs] == b:
            lo = int(block_ptr[b])
            mats[b][qd - lo, qs - lo] -= w_
        else:
            ext[qd].append((qs, w_))
    ext_ptr = np.zeros(n + 1, dtype=np.intp)
    for q in range(n):
        ext_ptr[q + 1] = ext_ptr[q] + len(ext[q])
    inv_ptr = np.zeros(len(blocks) + 1, dtype=np.intp)
    parts = [np.zeros(0)]
    for b, mat in enumerate(mats):
        size = len(mat) if len(mat) > 1 or dense else 0
        inv_ptr[b + 1] = inv_ptr[b] + size * size
        if size:
            parts.append(np.linalg.inv(mat).ravel())
    return SolvePlan(perm, dense, block_ptr, ext_ptr,
                     np.array([q for e in ext for q, _ in e], dtype=np.intp),
                     np.array([w_ for e in ext for _, w_ in e], dtype=float), inv_ptr, np.concatenate(parts))


@_jit_numpy_errors
def continuous(k0: int, k1: int, steps: int, record: bool, h: float, substeps: int, y: np.ndarray,
               ref_p: np.ndarray, ref_v: np.ndarray, ref_a: np.ndarray,
               exp_lead: bool, lead0: np.ndarray, decay: float, em: np.ndarray, xm: np.ndarray,
               kappa: np.ndarray, slot_src: np.ndarray, slot_w: np.ndarray, swd: np.ndarray, a_lead: np.ndarray,
               perm: np.ndarray, dense: bool, block_ptr: np.ndarray, ext_ptr: np.ndarray, ext_src: np.ndarray,
               ext_w: np.ndarray, inv_ptr: np.ndarray, inv: np.ndarray, rcoef: np.ndarray,
               const: np.ndarray, amp: np.ndarray, u_omega: np.ndarray, u_phase: np.ndarray, u_inv: np.ndarray,
               table: np.ndarray, hold: np.ndarray, has_random: bool, sin_m: np.ndarray, cos_m: np.ndarray,
               out_p: np.ndarray, out_v: np.ndarray, out_a: np.ndarray, out_u: np.ndarray, out_xi: np.ndarray,
               out_zeta: np.ndarray, out_x: np.ndarray, out_d: np.ndarray) -> None:
    """Control steps ``k0 .. k1-1`` of the continuous mode: record tick k's sample, then ``substeps``
    RK4 steps in place.

    Structure of arrays, axis first and flat: element ``x = c (N+1) + i`` is agent i's axis c, agents
    in solving order (:class:`SolvePlan`; agent ``perm[q]`` at position q, the samples written back
    in the mission's order), ``x = c (N+1) + N`` the leader's. ``y`` ``(2 + S, d (N+1))`` the state
    [p, v, the law's S state variables] (the leader's elements unused: its state is its reference);
    ``rcoef`` ``(d, R)`` per axis the coefficients of the law's ``rate``; the bank's per-axis arrays ``(d (N+1),)``, zero at the leader's elements; the leader's reference at
    the stage times (:func:`stage_times`), ``ref_*`` ``(d, (k1 - k0) substeps 3)``, unless
    ``exp_lead``: then the leader is :class:`leader.profile.ExpAccel` (``lead0`` its ``p0, v0, a0``,
    ``(3, d)``; ``decay``), evaluated here in closed form (``em, xm``: :func:`exp_tables`), and
    ``ref_*`` are not read; ``sin_m, cos_m`` ``(2 substeps + 1, d (N+1))`` the sine and
    cosine of ``omega m hf / 2``; ``u_omega, u_phase, u_inv`` the distinct sinusoids and each
    element's (:func:`sine_pairs`: each sine and cosine of a control step once per distinct pair,
    and not once per agent and axis that has it).

    The law's gains are per axis and ``L1`` acts on each axis alone: the axes are independent, and
    every element-wise step of a stage runs over all axes at once, in one loop of ``d (N+1)``
    (a few agents: one loop of 15 instead of three of 4), the leader's elements computed and then
    overwritten; the neighbour sums and ``L1 a = b`` go axis by axis. Per stage: the stage's input
    (``y + coef k_prev``) of the positions and velocities, which the neighbours read; the
    disturbance ``d(t)`` (``DisturbanceBank.value_at``), its sinusoids rotated from their phase at
    ``t_k`` by the angle-addition formula (a few ulp from ``sin(omega t + phase)``) and shared by
    the two mid-step stages; agent by agent, the errors, the gains' stage input and rates and
    ``b``; then ``L1 a = b``. RK4's weighted sum ``k1 + 2 k2 + 2 k3 + k4`` is accumulated stage by
    stage in that order, so that each operation rounds as the numpy path's does. One function body,
    every array indexed in place: a sub-call or an array view costs reference counts on each array
    it touches, which at a few agents was most of the time."""
    d = ref_p.shape[0]
    n1 = y.shape[1] // d
    n = n1 - 1
    nx = d * n1
    slots = slot_src.shape[0]
    blocks = block_ptr.shape[0] - 1
    last_row = table.shape[1] - 1
    hf = h / substeps
    w6 = hf / 6.0
    # a stage's inputs, which the neighbours read (the leader's elements from ref_*) ...
    pin = np.zeros(nx)
    vin = np.zeros(nx)
    # ... the previous stage's slopes (the position's is the previous vin), RK4's running sums;
    # zero at first, so that the leader's elements stay finite
    sl_v = np.zeros(nx)
    ac_p = np.zeros(nx)
    ac_v = np.zeros(nx)
    # the law's state: y's rows 2 .. (S of them), its stage input, slopes and running sums, (S, 1, nx)
    ns = y.shape[0] - 2
    ys = y[2:].reshape(ns, 1, nx)
    xin = np.zeros((max(ns, 1), 1, nx))
    sl_x = np.zeros((max(ns, 1), 1, nx))
    ac_x = np.zeros((max(ns, 1), 1, nx))
    xi = np.zeros(nx)
    zeta = np.zeros(nx)
    bb = np.zeros(nx)
    rr = np.zeros(n)
    dist0 = np.zeros(nx)  # d(t) at the step's ends
    dist1 = np.zeros(nx)  # and its middle
    sin0 = np.empty(nx)
    cos0 = np.empty(nx)
    lp = np.empty(d)  # the leader's reference at the stage's time
    lv = np.empty(d)
    la = np.empty(d)
    e_k = 1.0  # exp(-decay t_k), expm1(-decay t_k): the closed-form leader's, rotated to each stage time
    x_k = 0.0
    inv_decay = 1.0 / decay if decay != 0.0 else 0.0
    snu = np.empty(u_omega.shape[0])
    csu = np.empty(u_omega.shape[0])
    coef = (0.0, 0.5 * hf, 0.5 * hf, hf)
    wsum = (1.0, 2.0, 2.0, 1.0)
    for k in range(k0, k1):
        q = k - k0
        t = k * h
        final = k == steps
        if exp_lead and decay != 0.0:
            e_k = math.exp(-decay * t)
            x_k = math.expm1(-decay * t)
        for u in range(u_omega.shape[0]):
            th = u_omega[u] * t + u_phase[u]
            snu[u] = math.sin(th)
            csu[u] = math.cos(th)
        for x in range(nx):
            sin0[x] = snu[u_inv[x]]
            cos0[x] = csu[u_inv[x]]
        for j in range(substeps):
            for st in range(4):
                at = 0 if st == 0 else (1 if st < 3 else 2)  # the stage's time: ts, ts + hf/2, ts + hf
                ix = (q * substeps + j) * 3 + at  # its index in ref_*
                a = coef[st]
                ws = wsum[st]
                if st == 0:
                    for x in range(nx):
                        pin[x] = y[0, x]
                        vin[x] = y[1, x]
                else:
                    for x in range(nx):
                        pin[x] = y[0, x] + a * vin[x]  # the position's slope is the stage's velocity
                        vin[x] = y[1, x] + a * sl_v[x]
                # the leader at the stage's time: the two mid-step stages share it and, as the
                # disturbance, a substep's first stage has the previous substep's last
                if st != 2 and (st != 0 or j == 0 or not exp_lead):
                    if exp_lead:
                        # ExpAccel.__call__'s arithmetic; exp and expm1 of -decay tt by the addition
                        # formulas from t_k's (tt = t_k + m hf / 2 up to rounding): a few ulp
                        tt = _stage_time(t, j, at, hf)
                        m = 2 * j + at
                        if decay == 0.0:
                            ee, i1, i2 = 1.0, tt, 0.5 * tt * tt
                        else:
                            ee = e_k * em[m]
                            i1 = -(x_k * em[m] + xm[m]) * inv_decay
                            i2 = (tt - i1) * inv_decay
                        for c in range(d):
                            lp[c] = lead0[0, c] + lead0[1, c] * tt + lead0[2, c] * i2
                            lv[c] = lead0[1, c] + lead0[2, c] * i1
                            la[c] = lead0[2, c] * ee
                    else:
                        for c in range(d):
                            lp[c] = ref_p[c, ix]
                            lv[c] = ref_v[c, ix]
                            la[c] = ref_a[c, ix]
                for c in range(d):
                    pin[c * n1 + n] = lp[c]
                    vin[c * n1 + n] = lv[c]
                # the second mid-step stage has the first's disturbance; without random terms, a
                # substep's first stage has the previous substep's last (the same time, rotation m)
                if st != 2 and (st != 0 or j == 0 or has_random):
                    m = 2 * j + at
                    if at == 1:
                        for x in range(nx):
                            dist1[x] = const[x] + amp[x] * (sin0[x] * cos_m[m, x] + cos0[x] * sin_m[m, x])
                    else:
                        for x in range(nx):
                            dist0[x] = const[x] + amp[x] * (sin0[x] * cos_m[m, x] + cos0[x] * sin_m[m, x])
                    if has_random:
                        kd = int(math.floor(_stage_time(t, j, at, hf) / h + 1e-9))
                        for c in range(d):
                            for i in range(n):
                                idx = kd // hold[i]
                                if at == 1:
                                    dist1[c * n1 + i] += table[i, idx if idx < last_row else last_row, c]
                                else:
                                    dist0[c * n1 + i] += table[i, idx if idx < last_row else last_row, c]
                for c in range(d):
                    base = c * n1
                    lac = la[c]
                    for i in range(n):
                        x = base + i
                        s_ = base + slot_src[0, i]
                        w = slot_w[0, i]
                        sp = w * pin[s_]
                        sv = w * vin[s_]
                        for s in range(1, slots):
                            s_ = base + slot_src[s, i]
                            w = slot_w[s, i]
                            sp += w * pin[s_]
                            sv += w * vin[s_]
                        ki = kappa[i]
                        if st == 0:
                            for s in range(ns):
                                xin[s, 0, x] = y[2 + s, x]
                        else:
                            for s in range(ns):
                                xin[s, 0, x] = y[2 + s, x] + a * sl_x[s, 0, x]
                        di = dist1[x] if at == 1 else dist0[x]
                        # the law's continuous-time form (law_rate): agent i's row of L1 vdot = b
                        row, e, z, xr = law_rate(ki, pin[x], vin[x], sp, sv, swd[x], a_lead[i] * lac + ki * di,
                                                 law_load(xin, 0, x), rcoef[c])
                        xi[x] = e
                        zeta[x] = z
                        bb[x] = row
                        law_store(sl_x, 0, x, xr)
                    # the accelerations: L1 a = b (SolvePlan), this axis
                    if dense:
                        for r_ in range(n):
                            acc = 0.0
                            row = r_ * n
                            for i in range(n):
                                acc += inv[row + i] * bb[base + i]
                            sl_v[base + r_] = acc
                    elif blocks == n:  # every block a single agent (a tree, a chain): forward substitution
                        for p_ in range(n):
                            acc = bb[base + p_]
                            for e_ in range(ext_ptr[p_], ext_ptr[p_ + 1]):
                                acc += ext_w[e_] * sl_v[base + ext_src[e_]]
                            sl_v[base + p_] = acc / kappa[p_]
                    else:
                        for blk in range(blocks):
                            lo = block_ptr[blk]
                            hi = block_ptr[blk + 1]
                            for p_ in range(lo, hi):
                                acc = bb[base + p_]
                                for e_ in range(ext_ptr[p_], ext_ptr[p_ + 1]):
                                    acc += ext_w[e_] * sl_v[base + ext_src[e_]]
                                rr[p_] = acc
                            if hi - lo == 1:
                                sl_v[base + lo] = rr[lo] / kappa[lo]
                            else:
                                size = hi - lo
                                off = inv_ptr[blk]
                                for r_ in range(size):
                                    acc = 0.0
                                    row = off + r_ * size
                                    for i in range(size):
                                        acc += inv[row + i] * rr[lo + i]
                                    sl_v[base + lo + r_] = acc
                # RK4's running sums (the leader's elements too: finite, unused)
                if st == 0:
                    for x in range(nx):
                        ac_p[x] = vin[x]
                        ac_v[x] = sl_v[x]
                    for s in range(ns):
                        for x in range(nx):
                            ac_x[s, 0, x] = sl_x[s, 0, x]
                else:
                    for x in range(nx):
                        ac_p[x] = ac_p[x] + ws * vin[x]
                        ac_v[x] = ac_v[x] + ws * sl_v[x]
                    for s in range(ns):
                        for x in range(nx):
                            ac_x[s, 0, x] = ac_x[s, 0, x] + ws * sl_x[s, 0, x]
                if st == 0 and j == 0 and (record or final):  # tick k's sample
                    r = k if record else 0
                    for c in range(d):
                        for i in range(n):
                            x = c * n1 + i
                            ag = perm[i]
                            out_p[r, ag, c] = pin[x]
                            out_v[r, ag, c] = vin[x]
                            out_a[r, ag, c] = sl_v[x]
                            out_u[r, ag, c] = sl_v[x] - dist0[x]
                            out_xi[r, ag, c] = xi[x]
                            out_zeta[r, ag, c] = zeta[x]
                            law_record(out_x, r, ag, c, law_load(ys, 0, x))
                            out_d[r, ag, c] = dist0[x]
                if final:
                    return
            for x in range(nx):
                y[0, x] = y[0, x] + w6 * ac_p[x]
                y[1, x] = y[1, x] + w6 * ac_v[x]
            for s in range(ns):
                for x in range(nx):
                    y[2 + s, x] = y[2 + s, x] + w6 * ac_x[s, 0, x]


def exp_tables(decay: float, h: float, substeps: int) -> tuple[np.ndarray, np.ndarray]:
    """``exp`` and ``expm1`` of ``-decay m hf / 2`` for ``m = 0 .. 2 substeps``: :func:`continuous`'s
    closed-form leader at ``t_k + m hf / 2`` from its values at ``t_k`` (``e^(a+b) = e^a e^b``,
    ``e^(a+b) - 1 = (e^a - 1) e^b + (e^b - 1)``)."""
    x = -decay * (np.arange(2 * substeps + 1) * (0.5 * h / substeps))
    return np.exp(x), np.expm1(x)


def rotation_tables(omega: np.ndarray, h: float, substeps: int) -> tuple[np.ndarray, np.ndarray]:
    """``sin, cos`` of ``omega m hf / 2`` for ``m = 0 .. 2 substeps``, ``(2 substeps + 1, *omega.shape)``."""
    x = omega[None] * (np.arange(2 * substeps + 1).reshape(-1, *(1,) * omega.ndim) * (0.5 * h / substeps))
    return np.ascontiguousarray(np.sin(x)), np.ascontiguousarray(np.cos(x))
