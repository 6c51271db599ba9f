"""The reference simulator's compiled kernels (sim/kernel.py, numba) against its numpy path: the
discrete mode bit for bit, the continuous mode to round-off, across laws, feed-forward modes,
disturbances and leader profiles; and the numpy path taking over where the kernels cannot run."""

from __future__ import annotations

import subprocess
import zlib
import sys
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np
import pytest

from plant.disturbance import DisturbanceBank
from sim import refsim
from sim.setup import Mode, Setup
from tests.factories import build, random_mission
from tether import mission as ms

pytest.importorskip("numba")

from sim import kernel  # noqa: E402

FIELDS = ("t", "p", "v", "a", "u", "xi", "zeta", "kp", "kv", "d", "leader_p", "leader_v", "leader_a")
PROFILES = {
    "hold": {"kind": "hold"},
    "exp_accel": {"kind": "exp_accel", "a0": [0.4, -0.2], "decay": 0.3},
    "waypoints": {"kind": "waypoints", "points": [{"t": 0.0, "p": [0.0, 0.0]}, {"t": 1.5, "p": [1.0, 0.5]}]},
}


def _mixed(m: ms.Mission, rng: np.random.Generator) -> ms.Mission:
    """``m`` with every agent given one of the four disturbance models (all four present)."""
    kinds = [ms.Constant(value=rng.uniform(-0.5, 0.5, m.dim).tolist()),
             ms.Sinusoid(amplitude=rng.uniform(0, 0.4, m.dim).tolist(), omega=rng.uniform(0.2, 4, m.dim).tolist(),
                         phase=rng.uniform(0, 6, m.dim).tolist()),
             ms.BoundedRandom(bound=0.3, hold=0.2),
             ms.NoDisturbance()]
    agents = [msgspec.structs.replace(a, disturbance=kinds[k % 4]) for k, a in enumerate(m.agents)]
    return msgspec.structs.replace(m, agents=agents)


def _pair(m: ms.Mission, mode: Mode = "discrete", **kw: object) -> tuple[object, object]:
    return (refsim.simulate(m, mode, engine="numpy", **kw),  # type: ignore[arg-type]
            refsim.simulate(m, mode, engine="compiled", **kw))  # type: ignore[arg-type]


@pytest.mark.parametrize("law", ["sigma", "benchmark"])
@pytest.mark.parametrize("feedforward", ["measured", "commanded", "none"])
@pytest.mark.parametrize("disturbance", ["none", "constant", "sinusoid", "bounded_random", "mixed"])
def test_discrete_kernel_equals_the_numpy_path_bit_for_bit(law: str, feedforward: str, disturbance: str) -> None:
    rng = np.random.default_rng(zlib.crc32(f"{law}/{feedforward}/{disturbance}".encode()))
    m = random_mission(rng, 7, law=law, disturbance="sinusoid" if disturbance == "mixed" else disturbance,
                       duration=4.0, profile=PROFILES["exp_accel"])
    if disturbance == "mixed":
        m = _mixed(m, rng)
    m = msgspec.structs.replace(m, law=msgspec.structs.replace(m.law, feedforward=feedforward))
    a, b = _pair(m)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(b, f), getattr(a, f), err_msg=f)
    assert np.any(a.u != 0.0)


@pytest.mark.parametrize("profile", sorted(PROFILES))
@pytest.mark.parametrize("dim", [2, 3])
def test_discrete_kernel_equals_the_numpy_path_across_profiles_and_unrecorded(profile: str, dim: int) -> None:
    rng = np.random.default_rng(dim)
    prof = dict(PROFILES[profile])
    if dim == 3 and profile != "hold":
        prof = {"kind": "exp_accel", "a0": [0.4, -0.2, 0.1], "decay": 0.0} if profile == "exp_accel" else \
            {"kind": "waypoints", "points": [{"t": 0.0, "p": [0.0, 0.0, 0.0]}, {"t": 1.0, "p": [1.0, 0.0, 2.0]}]}
    m = _mixed(random_mission(rng, 9, dim=dim, duration=3.0, profile=prof), rng)
    a, b = _pair(m)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(b, f), getattr(a, f), err_msg=f)
    last = refsim.simulate(m, engine="compiled", record=False)
    assert last.t.shape == (1,)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(last, f)[0], getattr(a, f)[-1], err_msg=f)


def test_discrete_kernel_equals_the_numpy_path_on_section4() -> None:
    from tether.catalog import builtin_path

    m = ms.load(builtin_path("section4"))
    a, b = _pair(m, duration=60.0)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(b, f), getattr(a, f), err_msg=f)


@pytest.mark.parametrize("law", ["sigma", "benchmark"])
@pytest.mark.parametrize("disturbance", ["none", "sinusoid", "mixed"])
def test_continuous_kernel_equals_the_numpy_path_to_round_off(law: str, disturbance: str) -> None:
    rng = np.random.default_rng(zlib.crc32(f"{law}/{disturbance}/continuous".encode()))
    m = random_mission(rng, 5, law=law, disturbance="sinusoid" if disturbance == "mixed" else disturbance,
                       duration=2.0, profile=PROFILES["waypoints"])
    if disturbance == "mixed":
        m = _mixed(m, rng)
    a, b = _pair(m, "continuous", substeps=4)
    # the sinusoids are rotated from each tick's phase (angle addition) and L1^-1 is applied in a
    # fixed order: a few ulp per stage, not bit for bit
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        np.testing.assert_allclose(y, x, rtol=1e-12, atol=1e-12 * max(1.0, float(np.abs(x).max())), err_msg=f)
    # the recorded disturbance is evaluated at the tick itself, as the numpy path does: exactly
    np.testing.assert_array_equal(b.d, a.d)
    np.testing.assert_array_equal(b.leader_p, a.leader_p)


@pytest.mark.parametrize("profile", ["hold", "exp_accel", "exp_accel_3d", "waypoints"])
def test_continuous_kernel_equals_the_numpy_path_across_leader_profiles(profile: str) -> None:
    """The exponential profile (and a hold, its decay 0) is evaluated in the kernel in closed form,
    any other by numpy at the stage times: both to round-off, over a longer run (the closed form is
    rotated from each control tick, so that it cannot drift)."""
    rng = np.random.default_rng(zlib.crc32(f"{profile}/continuous".encode()))
    dim = 3 if profile == "exp_accel_3d" else 2
    prof = {"kind": "exp_accel", "a0": [0.4, -0.2, 0.1], "decay": 0.0} if dim == 3 else PROFILES[profile]
    m = _mixed(random_mission(rng, 6, dim=dim, duration=8.0, profile=prof), rng)
    a, b = _pair(m, "continuous", substeps=5)
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        np.testing.assert_allclose(y, x, rtol=1e-12, atol=1e-12 * max(1.0, float(np.abs(x).max())), err_msg=f)
    assert np.any(a.leader_a != 0.0) or profile == "hold"


def _graph_mission(n: int, edges: dict[tuple[int, int], float], rng: np.random.Generator) -> ms.Mission:
    """``n`` agents (3D, sinusoids and random gusts mixed) on these edges, the leader ``n + 1``."""
    m = random_mission(rng, n, dim=3, disturbance="sinusoid", duration=1.0, profile={"kind": "hold"})
    raw = msgspec.to_builtins(_mixed(m, rng))
    raw["edges"] = [{"from": s, "to": d, "weight": w} for (s, d), w in edges.items()]
    return build(raw)


def _chain_with_short_cycles(n: int, rng: np.random.Generator) -> dict[tuple[int, int], float]:
    """A tree hanging from the leader, each agent hearing one of the five before it, plus a few
    agents hearing the agent two after them (cycles of two or three)."""
    edges = {(n + 1, 1): 1.0}
    for i in range(2, n + 1):
        edges[(int(rng.integers(max(1, i - 5), i)), i)] = float(rng.uniform(0.5, 2.0))
    for i in rng.choice(np.arange(1, n - 2), size=n // 8, replace=False).tolist():
        edges.setdefault((i + 2, i), 0.5)
    return edges


def test_the_solve_plan_orders_blocks_after_what_they_hear_and_solves_l1() -> None:
    from tether import graph

    rng = np.random.default_rng(11)
    n = 60
    for edges, dense in ((_chain_with_short_cycles(n, rng), False),
                         ({(n + 1, 1): 1.0, **{(i, i % n + 1): 1.0 for i in range(1, n + 1)}}, True),  # a ring
                         ({(n + 1, 1): 1.0, **{(i, i + 1): 1.0 for i in range(1, n)}}, False)):  # a chain
        topo = Setup.of(_graph_mission(n, edges, rng)).topo
        plan = kernel.solve_plan(n, topo.src, topo.dst, topo.weight, topo.kappa)
        assert plan.dense is dense
        assert sorted(plan.perm.tolist()) == list(range(n))
        # every in-edge from outside a block comes from an earlier position
        for b in range(len(plan.block_ptr) - 1):
            lo, hi = plan.block_ptr[b], plan.block_ptr[b + 1]
            assert np.all(plan.ext_src[plan.ext_ptr[lo]:plan.ext_ptr[hi]] < lo)
        # the plan solves L1 a = b (as the kernel does, in Python)
        l1, _ = graph.partition(topo.adjacency)
        rhs = rng.normal(size=n)
        bq = rhs[plan.perm]
        a = np.zeros(n)
        for b in range(len(plan.block_ptr) - 1):
            lo, hi = int(plan.block_ptr[b]), int(plan.block_ptr[b + 1])
            r = np.array([bq[q] + sum(plan.ext_w[x] * a[plan.ext_src[x]]
                                      for x in range(plan.ext_ptr[q], plan.ext_ptr[q + 1])) for q in range(lo, hi)])
            size = hi - lo
            if size == 1 and not plan.dense:
                a[lo] = r[0] / topo.kappa[plan.perm[lo]]
            else:
                inv = plan.inv[plan.inv_ptr[b]:plan.inv_ptr[b] + size * size].reshape(size, size)
                a[lo:hi] = inv @ r
        out = np.empty(n)
        out[plan.perm] = a
        np.testing.assert_allclose(out, np.linalg.solve(l1, rhs), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("graph_kind", ["chain with short cycles", "ring", "tree"])
def test_continuous_kernel_equals_the_numpy_path_on_large_graphs(graph_kind: str) -> None:
    """Beyond DENSE_SOLVE agents: block by block (a tree with short cycles), one strongly
    connected graph (a ring, the whole inverse) and a graph without cycles (a tree, every block a
    single agent: forward substitution); agents renumbered in solving order."""
    rng = np.random.default_rng(zlib.crc32(graph_kind.encode()))
    n = kernel.DENSE_SOLVE + 8
    if graph_kind == "ring":
        edges = {(n + 1, 1): 1.0, **{(i, i % n + 1): 1.0 for i in range(1, n + 1)}}
    elif graph_kind == "tree":  # each agent hears one or two earlier agents, weights not 1 (kappa_i != 1)
        edges = {(n + 1, 1): 1.0, **{(int(j), i): float(rng.uniform(0.5, 2.0))
                                     for i in range(2, n + 1) for j in rng.choice(np.arange(1, i), size=min(i - 1, 2))}}
    else:
        edges = _chain_with_short_cycles(n, rng)
    m = _graph_mission(n, edges, rng)
    topo = Setup.of(m).topo
    plan = kernel.solve_plan(n, topo.src, topo.dst, topo.weight, topo.kappa)
    assert plan.dense is (graph_kind == "ring")
    assert (len(plan.block_ptr) - 1 == n) is (graph_kind == "tree")
    a, b = _pair(m, "continuous", substeps=4)
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        np.testing.assert_allclose(y, x, rtol=1e-11, atol=1e-11 * max(1.0, float(np.abs(x).max())), err_msg=f)
    np.testing.assert_array_equal(b.d, a.d)


def test_continuous_kernel_refuses_what_the_continuous_mode_refuses() -> None:
    m = random_mission(np.random.default_rng(1), 3, duration=1.0)
    m = msgspec.structs.replace(m, law=msgspec.structs.replace(m.law, feedforward="commanded"))
    with pytest.raises(ValueError, match="feedforward"):
        refsim.simulate(m, "continuous", engine="compiled")


@dataclass(frozen=True)
class _Gusts(DisturbanceBank):
    """A bank with a model the kernels do not know (as a later disturbance model would be)."""

    gust: float = 0.0


def test_a_bank_layout_the_kernels_do_not_know_keeps_the_numpy_path() -> None:
    m = random_mission(np.random.default_rng(2), 3, disturbance="sinusoid", duration=1.0)
    s = Setup.of(m)
    assert kernel.supports(s.dist)
    d = s.dist
    odd = _Gusts(d.h, d.const, d.amp, d.omega, d.phase, d.table, d.hold_ticks, gust=1.0)
    assert not kernel.supports(odd)
    odd_setup = Setup(s.mission, s.topo, s.bound, s.ref, odd, s.offsets, s.sum_wdelta, s.p0, s.v0)
    assert not refsim.takes_kernel(odd_setup, "auto", None)
    with pytest.raises(ValueError, match="cannot run"):
        refsim.takes_kernel(odd_setup, "compiled", None)
    # a live view (on_tick) is served sample by sample by the numpy loop
    assert not refsim.takes_kernel(s, "auto", lambda run, r: None)


def test_without_numba_the_numpy_path_runs() -> None:
    root = Path(__file__).resolve().parents[1]
    code = ("import sys; sys.modules['numba'] = None\n"  # `import numba` now raises ImportError
            "from sim import kernel, refsim\n"
            "from tests.factories import random_mission\n"
            "import numpy as np\n"
            "assert not kernel.AVAILABLE\n"
            "m = random_mission(np.random.default_rng(3), 3, disturbance='sinusoid', duration=1.0)\n"
            "run = refsim.simulate(m)\n"
            "assert np.isfinite(run.p).all()\n"
            "try:\n"
            "    refsim.simulate(m, engine='compiled')\n"
            "except ValueError as e:\n"
            "    print('refused:', e)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root,
                          env={"PYTHONPATH": str(root), "PATH": ""}, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "refused:" in done.stdout and "numba" in done.stdout


def _threads_equal_numpy(m: ms.Mission, threads: int) -> None:
    """The compiled discrete mode on ``threads`` of numba's threads equals the numpy path bit for bit,
    recorded and unrecorded."""
    a = refsim.simulate(m, engine="numpy")
    b = refsim.simulate(m, engine="compiled", threads=threads)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(b, f), getattr(a, f), err_msg=f)
    last = refsim.simulate(m, engine="compiled", record=False, threads=threads)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(last, f)[0], getattr(a, f)[-1], err_msg=f)


@pytest.mark.slow  # compiles the parallel kernel, about a minute of CPU on a cold cache
@pytest.mark.parametrize("threads", [2, 3])
def test_discrete_kernel_on_threads_equals_the_numpy_path_bit_for_bit(threads: int) -> None:
    # blocks of agents on numba's threads (prange): an agent's arithmetic does not depend on the split
    rng = np.random.default_rng(40 + threads)
    m = _mixed(random_mission(rng, 37, duration=2.0, profile=PROFILES["exp_accel"]), rng)
    _threads_equal_numpy(m, threads)


def test_sine_pairs_tell_apart_what_the_bits_tell_apart() -> None:
    # agents sharing a sinusoid share its sine; -0.0 and 0.0 phases give different bits at t = 0
    # (omega < 0: -0.0 + -0.0 is -0.0, -0.0 + 0.0 is 0.0) and stay apart
    omega = np.array([[1.0, 1.0, -2.0, -2.0, 3.0]])
    phase = np.array([[0.5, 0.5, -0.0, 0.0, 0.5]])
    u_omega, u_phase, inv = kernel.sine_pairs(omega, phase)
    assert len(u_omega) == 4
    np.testing.assert_array_equal(u_omega[inv], omega)
    assert (np.signbit(u_phase[inv]) == np.signbit(phase)).all()
    assert inv[0, 0] == inv[0, 1] and inv[0, 2] != inv[0, 3]


def test_discrete_kernel_with_shared_and_distinct_sinusoids_equals_the_numpy_path() -> None:
    rng = np.random.default_rng(77)
    m = random_mission(rng, 12, disturbance="sinusoid", duration=3.0, profile=PROFILES["exp_accel"])
    shared = m.agents[0].disturbance
    agents = [msgspec.structs.replace(a, disturbance=shared) if k % 2 else a for k, a in enumerate(m.agents)]
    m = msgspec.structs.replace(m, agents=agents)
    a, b = _pair(m)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(b, f), getattr(a, f), err_msg=f)


def test_the_kernels_sines_are_numpys_bits_over_every_argument_scale() -> None:
    # the kernel takes sine and cosine of one argument in one loop body, which LLVM turns into one
    # call of libm's sincos: its bits must be np.sin's and np.cos's, small arguments and huge ones
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.uniform(-s, s, 40_000) for s in (1e-8, 1.0, 10.0, 1e3, 1e6, 1e12, 1e300)]
                       + [np.array([0.0, -0.0, np.pi, -np.pi / 2, 2.0 ** 30, 1e308])])
    omega, phase = np.ones_like(x), x
    snu, csu = np.empty_like(x), np.empty_like(x)
    kernel._sines(0, 0, len(x), 10, True, 0.01, True, False, omega, phase, snu, csu)
    arg = omega * 0.0 + phase  # as the bank computes it at t = 0 (-0.0 becomes 0.0)
    np.testing.assert_array_equal(snu.view(np.int64), np.sin(arg).view(np.int64))
    np.testing.assert_array_equal(csu.view(np.int64), np.cos(arg).view(np.int64))


def test_discrete_kernel_on_threads_with_every_agent_its_own_sines_equals_the_numpy_path() -> None:
    # most sines distinct: each block of agents takes its own agents' sines (kernel.discrete_parallel's `own`)
    rng = np.random.default_rng(91)
    m = random_mission(rng, 29, disturbance="sinusoid", duration=2.0, profile=PROFILES["exp_accel"])
    s = Setup.of(m)
    u_omega, _, _ = kernel.sine_pairs(s.dist.omega.T, s.dist.phase.T)
    assert 2 * len(u_omega) > m.n * m.dim  # the path under test
    for threads in (2, 3):
        _threads_equal_numpy(m, threads)
