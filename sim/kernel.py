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
* :func:`continuous` is the continuous mode's RK4 with the algebraic loop through ``L1^{-1}``, every
  stage in the kernel; the leader's profile is evaluated by numpy beforehand at every stage time
  (:func:`stage_times`). The sinusoids are rotated from their phase at each control tick by the
  angle-addition formula (two sines a control step per axis instead of forty) and the two mid-step
  stages share theirs, and the matrix-vector product sums in a fixed order where numpy calls BLAS:
  it equals the numpy path to round-off, not bit for bit.

The disturbance bank is read from its arrays (:func:`bank_arrays`); a bank whose layout this module
does not know (a model added to :mod:`plant.disturbance` since) makes :func:`supports` say no, and
the simulator keeps its numpy path, which goes through the bank's own methods.

Without numba installed, :data:`AVAILABLE` is False and nothing here is compiled.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import numpy as np

from plant.disturbance import DisturbanceBank

numba: Any
try:  # the [fast] extra
    import numba
except ImportError:  # exercised where numba is missing (tests/test_refsim_kernel.py hides it)
    numba = None

AVAILABLE = numba is not None
"""Whether the compiled kernels can run here (numba imports)."""

_BANK_FIELDS = frozenset({"h", "const", "amp", "omega", "phase", "table", "hold_ticks", "_cv_s", "_cv_c", "_cp_s",
                          "_cp_c", "_has_sine", "_has_random", "_has_const"})
"""The :class:`DisturbanceBank` layout the kernels evaluate."""


def supports(dist: DisturbanceBank) -> bool:
    """Whether the kernels evaluate ``dist`` exactly as its own methods do (its layout is known)."""
    return (AVAILABLE and type(dist) is DisturbanceBank
            and frozenset(f.name for f in dataclasses.fields(dist)) == _BANK_FIELDS
            # one layer of each model: a summed disturbance of several sinusoids or random terms
            # ((L, n, d) and (R, n, M, d) arrays) is evaluated by the numpy path
            and dist.amp.ndim == 2 and dist.table.ndim == 3 and dist.hold_ticks.ndim == 1)


def bank_arrays(dist: DisturbanceBank) -> tuple[Any, ...]:
    """The bank as the kernels take it: its arrays, flags and coefficients."""
    return (dist.const, dist.amp, dist.omega, dist.phase, dist.table, dist.hold_ticks.astype(np.int64),
            dist._cv_s, dist._cv_c, dist._cp_s, dist._cp_c,
            bool(dist._has_sine), bool(dist._has_random), bool(dist._has_const))


def _jit(fn: Callable[..., Any]) -> Callable[..., Any]:
    # no fastmath: no reassociation, no fused multiply-adds, so each operation rounds as numpy's does
    return fn if numba is None else numba.njit(cache=True, nogil=True)(fn)


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
    if has_sine or ((record or last) and not zero_d):
        tk = k * h
        for u in range(lo, hi):
            snu[u] = math.sin(u_omega[u] * tk + u_phase[u])
        if has_sine and not last:
            for u in range(lo, hi):
                csu[u] = math.cos(u_omega[u] * tk + u_phase[u])


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
           feed: int, decay: float, gp_gain: float, gv_gain: float,
           pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, meas: np.ndarray, gains: np.ndarray,
           const: np.ndarray, amp: np.ndarray, omega: np.ndarray, phase: np.ndarray, table: np.ndarray,
           hold: np.ndarray, cv_s: np.ndarray, cv_c: np.ndarray, cp_s: np.ndarray, cp_c: np.ndarray,
           has_sine: bool, has_random: bool, has_const: bool,
           out_p: np.ndarray, out_v: np.ndarray, out_a: np.ndarray, out_u: np.ndarray, out_xi: np.ndarray,
           out_zeta: np.ndarray, out_kp: np.ndarray, out_kv: np.ndarray, out_d: np.ndarray,
           sp: np.ndarray, sv: np.ndarray, sa: np.ndarray, dvb: np.ndarray, dpb: np.ndarray,
           snb: np.ndarray, csb: np.ndarray, inv: np.ndarray, snu: np.ndarray, csu: np.ndarray) -> None:
    """Tick k of agents ``lo .. hi-1``, axis by axis: the neighbour sums slot by slot (as
    :func:`tether.graph.neighbour_sums`), the disturbance increments, then the law, the gains and
    the plant element-wise. Reads tick k's half of the double buffers, writes tick k+1's half and
    the rows ``lo .. hi`` of everything else: blocks of agents can run at the same time."""
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
        if has_sine or (keep and not zero_d):
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
                    a1 = cv_s[c, lo:hi]
                    a2 = cv_c[c, lo:hi]
                    for i in range(m):
                        dvs[i] = dvs[i] + sns[i] * a1[i] + css[i] * a2[i]
                    a1 = cp_s[c, lo:hi]
                    a2 = cp_c[c, lo:hi]
                    for i in range(m):
                        dps[i] = dps[i] + sns[i] * a1[i] + css[i] * a2[i]
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
        g0 = gains[0, c, lo:hi]
        g1 = gains[1, c, lo:hi]
        # the law (tether's agent.law.errors and control), element-wise: xi into xs, zeta into zs, u into us
        for i in range(m):
            xs[i] = ka[i] * p[i] - xs[i] - sw[i]
        for i in range(m):
            zs[i] = ka[i] * v[i] - zs[i]
        if feed == 2:
            for i in range(m):
                us[i] = (0.0 - g0[i] * xs[i] - g1[i] * zs[i]) / ka[i]
        else:
            for i in range(m):
                us[i] = (us[i] - g0[i] * xs[i] - g1[i] * zs[i]) / ka[i]
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
                out_kp[r, q, c] = g0[i]
                out_kv[r, q, c] = g1[i]
                if zero_d:
                    out_d[r, q, c] = 0.0
                else:
                    out_d[r, q, c] = (const[c, q] + amp[c, q] * sns[i]
                                      + (_random(table, hold, q, k, c) if has_random else 0.0))
        if last:
            continue
        # the exact gain step, then plant.double_integrator.step
        for i in range(m):
            g0[i] = 1.0 + (g0[i] - 1.0) * decay + gp_gain * (xs[i] * xs[i])
        for i in range(m):
            g1[i] = 1.0 + (g1[i] - 1.0) * decay + gv_gain * (zs[i] * zs[i])
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
             feed: int, decay: float, gp_gain: float, gv_gain: float,
             lp: np.ndarray, lv: np.ndarray, la: np.ndarray,
             pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, meas: np.ndarray, gains: np.ndarray,
             const: np.ndarray, amp: np.ndarray, omega: np.ndarray, phase: np.ndarray, table: np.ndarray,
             hold: np.ndarray, cv_s: np.ndarray, cv_c: np.ndarray, cp_s: np.ndarray, cp_c: np.ndarray,
             has_sine: bool, has_random: bool, has_const: bool,
             out_p: np.ndarray, out_v: np.ndarray, out_a: np.ndarray, out_u: np.ndarray, out_xi: np.ndarray,
             out_zeta: np.ndarray, out_kp: np.ndarray, out_kv: np.ndarray, out_d: np.ndarray,
             u_omega: np.ndarray, u_phase: np.ndarray, inv: np.ndarray, blocks: int) -> None:
    """Ticks ``k0 .. k1-1`` of the discrete mode (``feed``: 0 measured, 1 commanded, 2 none), on
    one thread (``blocks`` is :func:`discrete_parallel`'s, unused here).

    Structure of arrays, axis first: ``pos, vel, acc`` ``(2, d, N+1)`` (double-buffered: ``[k % 2]``
    is tick k's; column N the leader), ``meas`` ``(d, N)``, ``gains`` ``(2, d, N)`` [Kp, Kv], the
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
        _block(k, 0, n, steps, record, h, hh2, kappa, slot_src, slot_w, swd, feed, decay, gp_gain, gv_gain,
               pos, vel, acc, meas, gains, const, amp, omega, phase, table, hold, cv_s, cv_c, cp_s, cp_c,
               has_sine, has_random, has_const, out_p, out_v, out_a, out_u, out_xi, out_zeta, out_kp, out_kv,
               out_d, sp, sv, sa, dvb, dpb, snb, csb, inv, snu, csu)


@_jit_parallel
def discrete_parallel(k0: int, k1: int, steps: int, record: bool, h: float, hh2: float,
                      kappa: np.ndarray, slot_src: np.ndarray, slot_w: np.ndarray, swd: np.ndarray,
                      feed: int, decay: float, gp_gain: float, gv_gain: float,
                      lp: np.ndarray, lv: np.ndarray, la: np.ndarray,
                      pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, meas: np.ndarray, gains: np.ndarray,
                      const: np.ndarray, amp: np.ndarray, omega: np.ndarray, phase: np.ndarray, table: np.ndarray,
                      hold: np.ndarray, cv_s: np.ndarray, cv_c: np.ndarray, cp_s: np.ndarray, cp_c: np.ndarray,
                      has_sine: bool, has_random: bool, has_const: bool,
                      out_p: np.ndarray, out_v: np.ndarray, out_a: np.ndarray, out_u: np.ndarray,
                      out_xi: np.ndarray, out_zeta: np.ndarray, out_kp: np.ndarray, out_kv: np.ndarray,
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
    for k in range(k0, k1):
        cur = k & 1
        for c in range(d):
            pos[cur, c, n] = lp[k, c]
            vel[cur, c, n] = lv[k, c]
            acc[cur, c, n] = la[k, c]
        if pairs >= 64 * blocks:
            for b in numba.prange(blocks):
                _sines(k, b * pairs // blocks, (b + 1) * pairs // blocks, steps, record, h, has_sine, zero_d,
                       u_omega, u_phase, snu, csu)
        else:
            _sines(k, 0, pairs, steps, record, h, has_sine, zero_d, u_omega, u_phase, snu, csu)
        for b in numba.prange(blocks):
            lo = min(b * size, n)
            hi = min(lo + size, n)
            _block(k, lo, hi, steps, record, h, hh2, kappa, slot_src, slot_w, swd, feed, decay, gp_gain, gv_gain,
                   pos, vel, acc, meas, gains, const, amp, omega, phase, table, hold, cv_s, cv_c, cp_s, cp_c,
                   has_sine, has_random, has_const, out_p, out_v, out_a, out_u, out_xi, out_zeta, out_kp, out_kv,
                   out_d, sp, sv, sa, dvb, dpb, snb, csb, inv, snu, csu)


def stage_times(k0: int, k1: int, h: float, substeps: int) -> np.ndarray:
    """The times at which the continuous mode evaluates its right-hand side over control steps
    ``k0 .. k1-1``, ``(k1 - k0, substeps, 3)``: ``ts``, ``ts + hf/2``, ``ts + hf`` with
    ``ts = k h + j hf``, computed as the numpy path computes them."""
    hf = h / substeps
    t = np.arange(k0, k1)[:, None] * h
    ts = t + np.arange(substeps)[None, :] * hf
    return np.stack([ts, ts + 0.5 * hf, ts + hf], axis=2)


@_jit
def _dist_at(t: float, m: int, sin0: np.ndarray, cos0: np.ndarray, sin_m: np.ndarray, cos_m: np.ndarray,
             h: float, const: np.ndarray, amp: np.ndarray, table: np.ndarray, hold: np.ndarray, has_random: bool,
             out: np.ndarray) -> None:
    """``d(t)`` (``DisturbanceBank.value_at``) at ``t = t_k + m hf / 2`` into ``out``: the sinusoids by
    the angle-addition formula from ``sin0, cos0`` (their phase at ``t_k``) and the tables
    ``sin_m, cos_m`` of ``omega m hf / 2`` (a few ulp from ``sin(omega t + phase)``: round-off)."""
    n, d = out.shape
    kd = int(math.floor(t / h + 1e-9)) if has_random else 0
    for i in range(n):
        for c in range(d):
            sn = sin0[i, c] * cos_m[m, i, c] + cos0[i, c] * sin_m[m, i, c]
            out[i, c] = const[i, c] + amp[i, c] * sn + (_random(table, hold, i, kd, c) if has_random else 0.0)


@_jit
def _rhs(y: np.ndarray, lp: np.ndarray, lv: np.ndarray, la: np.ndarray,
         kappa: np.ndarray, slot_src: np.ndarray, slot_w: np.ndarray, swd: np.ndarray, a_lead: np.ndarray,
         l1_inv: np.ndarray, gamma_p: float, gamma_v: float, sigma: float, dist: np.ndarray,
         dy: np.ndarray, xi: np.ndarray, zeta: np.ndarray, rhs_b: np.ndarray) -> None:
    """The continuous closed loop's right-hand side into ``dy`` (and the errors); ``y`` is
    ``(4, N, d)`` [p, v, Kp, Kv]; the leader's sample ``lp, lv, la``; the disturbance ``dist``."""
    _, n, d = y.shape
    slots = slot_src.shape[0]
    for i in range(n):
        ki = kappa[i]
        for c in range(d):
            sp = 0.0
            sv = 0.0
            for s in range(slots):
                j = slot_src[s, i]
                w = slot_w[s, i]
                pj = lp[c] if j == n else y[0, j, c]
                vj = lv[c] if j == n else y[1, j, c]
                if s == 0:
                    sp = w * pj
                    sv = w * vj
                else:
                    sp += w * pj
                    sv += w * vj
            e = ki * y[0, i, c] - sp - swd[i, c]
            z = ki * y[1, i, c] - sv
            xi[i, c] = e
            zeta[i, c] = z
            rhs_b[i, c] = a_lead[i] * la[c] + ki * dist[i, c] - y[2, i, c] * e - y[3, i, c] * z
    for i in range(n):
        for c in range(d):
            acc = 0.0
            for j in range(n):
                acc += l1_inv[i, j] * rhs_b[j, c]
            dy[0, i, c] = y[1, i, c]
            dy[1, i, c] = acc
            dy[2, i, c] = -sigma * (y[2, i, c] - 1.0) + gamma_p * (xi[i, c] * xi[i, c])
            dy[3, i, c] = -sigma * (y[3, i, c] - 1.0) + gamma_v * (zeta[i, c] * zeta[i, c])


@_jit
def continuous(k0: int, k1: int, steps: int, record: bool, h: float, substeps: int, y: np.ndarray,
               ref_p: np.ndarray, ref_v: np.ndarray, ref_a: np.ndarray, times: np.ndarray,
               kappa: np.ndarray, slot_src: np.ndarray, slot_w: np.ndarray, swd: np.ndarray, a_lead: np.ndarray,
               l1_inv: np.ndarray, gamma_p: float, gamma_v: float, sigma: float,
               const: np.ndarray, amp: np.ndarray, omega: np.ndarray, phase: np.ndarray, table: np.ndarray,
               hold: np.ndarray, has_random: bool, sin_m: np.ndarray, cos_m: np.ndarray,
               out_p: np.ndarray, out_v: np.ndarray, out_a: np.ndarray, out_u: np.ndarray, out_xi: np.ndarray,
               out_zeta: np.ndarray, out_kp: np.ndarray, out_kv: np.ndarray, out_d: np.ndarray) -> None:
    """Control steps ``k0 .. k1-1`` of the continuous mode: record tick k's sample, then ``substeps``
    RK4 steps of ``y`` in place. ``ref_*`` and ``times`` are ``(k1 - k0, substeps, 3, ...)`` (see
    :func:`stage_times`); ``sin_m, cos_m`` ``(2 substeps + 1, N, d)`` the sine and cosine of
    ``omega m hf / 2``. The disturbance is shared by the two mid-step stages (the same time)."""
    _, n, d = y.shape
    hf = h / substeps
    k1s = np.empty_like(y)
    k2s = np.empty_like(y)
    k3s = np.empty_like(y)
    k4s = np.empty_like(y)
    tmp = np.empty_like(y)
    xi = np.empty((n, d))
    zeta = np.empty((n, d))
    d0 = np.empty((n, d))
    dh = np.empty((n, d))
    b = np.empty((n, d))
    sin0 = np.empty((n, d))
    cos0 = np.empty((n, d))
    size = y.size
    yf = y.reshape(size)
    tmpf = tmp.reshape(size)
    k1f = k1s.reshape(size)
    k2f = k2s.reshape(size)
    k3f = k3s.reshape(size)
    k4f = k4s.reshape(size)
    for k in range(k0, k1):
        q = k - k0
        t = k * h
        for i in range(n):
            for c in range(d):
                th = omega[i, c] * t + phase[i, c]
                sin0[i, c] = math.sin(th)
                cos0[i, c] = math.cos(th)
        _dist_at(t, 0, sin0, cos0, sin_m, cos_m, h, const, amp, table, hold, has_random, d0)
        _rhs(y, ref_p[q, 0, 0], ref_v[q, 0, 0], ref_a[q, 0, 0], kappa, slot_src, slot_w, swd, a_lead, l1_inv,
             gamma_p, gamma_v, sigma, d0, k1s, xi, zeta, b)
        if record or k == steps:
            r = k if record else 0
            for i in range(n):
                for c in range(d):
                    out_p[r, i, c] = y[0, i, c]
                    out_v[r, i, c] = y[1, i, c]
                    out_a[r, i, c] = k1s[1, i, c]
                    out_u[r, i, c] = k1s[1, i, c] - d0[i, c]
                    out_xi[r, i, c] = xi[i, c]
                    out_zeta[r, i, c] = zeta[i, c]
                    out_kp[r, i, c] = y[2, i, c]
                    out_kv[r, i, c] = y[3, i, c]
                    out_d[r, i, c] = d0[i, c]
        if k == steps:
            break
        for j in range(substeps):
            if j:
                _dist_at(times[q, j, 0], 2 * j, sin0, cos0, sin_m, cos_m, h, const, amp, table, hold, has_random, d0)
                _rhs(y, ref_p[q, j, 0], ref_v[q, j, 0], ref_a[q, j, 0], kappa, slot_src, slot_w, swd, a_lead,
                     l1_inv, gamma_p, gamma_v, sigma, d0, k1s, xi, zeta, b)
            for e in range(size):
                tmpf[e] = yf[e] + 0.5 * hf * k1f[e]
            _dist_at(times[q, j, 1], 2 * j + 1, sin0, cos0, sin_m, cos_m, h, const, amp, table, hold, has_random, dh)
            _rhs(tmp, ref_p[q, j, 1], ref_v[q, j, 1], ref_a[q, j, 1], kappa, slot_src, slot_w, swd, a_lead,
                 l1_inv, gamma_p, gamma_v, sigma, dh, k2s, xi, zeta, b)
            for e in range(size):
                tmpf[e] = yf[e] + 0.5 * hf * k2f[e]
            _rhs(tmp, ref_p[q, j, 1], ref_v[q, j, 1], ref_a[q, j, 1], kappa, slot_src, slot_w, swd, a_lead,
                 l1_inv, gamma_p, gamma_v, sigma, dh, k3s, xi, zeta, b)
            for e in range(size):
                tmpf[e] = yf[e] + hf * k3f[e]
            _dist_at(times[q, j, 2], 2 * j + 2, sin0, cos0, sin_m, cos_m, h, const, amp, table, hold, has_random, d0)
            _rhs(tmp, ref_p[q, j, 2], ref_v[q, j, 2], ref_a[q, j, 2], kappa, slot_src, slot_w, swd, a_lead,
                 l1_inv, gamma_p, gamma_v, sigma, d0, k4s, xi, zeta, b)
            for e in range(size):
                yf[e] = yf[e] + (hf / 6.0) * (k1f[e] + 2.0 * k2f[e] + 2.0 * k3f[e] + k4f[e])


def rotation_tables(omega: np.ndarray, h: float, substeps: int) -> tuple[np.ndarray, np.ndarray]:
    """``sin, cos`` of ``omega m hf / 2`` for ``m = 0 .. 2 substeps``, ``(2 substeps + 1, N, d)``."""
    x = omega[None] * (np.arange(2 * substeps + 1)[:, None, None] * (0.5 * h / substeps))
    return np.ascontiguousarray(np.sin(x)), np.ascontiguousarray(np.cos(x))
