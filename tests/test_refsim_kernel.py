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
from tests.factories import random_mission
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


def _pair(m: ms.Mission, mode: refsim.Mode = "discrete", **kw: object) -> tuple[object, object]:
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
    s = refsim.Setup.of(m)
    assert kernel.supports(s.dist)
    d = s.dist
    odd = _Gusts(d.h, d.const, d.amp, d.omega, d.phase, d.table, d.hold_ticks, gust=1.0)
    assert not kernel.supports(odd)
    odd_setup = refsim.Setup(s.mission, s.topo, s.params, s.ref, odd, s.offsets, s.sum_wdelta, s.p0, s.v0)
    assert not refsim._compiled(odd_setup, "auto", None)
    with pytest.raises(ValueError, match="cannot run"):
        refsim._compiled(odd_setup, "compiled", None)
    # a live view (on_tick) is served sample by sample by the numpy loop
    assert not refsim._compiled(s, "auto", lambda run, r: None)


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


@pytest.mark.parametrize("threads", [2, 3])
def test_discrete_kernel_on_threads_equals_the_numpy_path_bit_for_bit(threads: int) -> None:
    # blocks of agents on numba's threads (prange): an agent's arithmetic does not depend on the split
    rng = np.random.default_rng(40 + threads)
    m = _mixed(random_mission(rng, 37, duration=2.0, profile=PROFILES["exp_accel"]), rng)
    a = refsim.simulate(m, engine="numpy")
    b = refsim.simulate(m, engine="compiled", threads=threads)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(b, f), getattr(a, f), err_msg=f)
    last = refsim.simulate(m, engine="compiled", record=False, threads=threads)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(last, f)[0], getattr(a, f)[-1], err_msg=f)


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
