"""A law of one's own (examples/custom_law): checked by ``tether check``, and equal bit for bit in
every engine, as the built-in laws are: the reference simulator's numpy path and compiled kernel,
the in-process engine and its compiled twin, and ``tether run --clock lockstep``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest

from agent import laws
from agent.laws import FormationLaw
from sim import lockstep, lockstep_kernel, refsim
from tether import mission as ms
from tether.node import load_mission
from tether.runfile import Run

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "custom_law" / "mission.toml"
SERIES = ("p", "v", "a", "u", "xi", "zeta", "kp", "kv", "d")


class PIParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    kp: float
    kv: float
    ki: float


def pi_step(ka: Any, p: Any, v: Any, sp: Any, sv: Any, sa: Any, sd: Any, x: tuple[Any], c: Any) -> tuple[Any, ...]:
    """PD with an integral of xi (one state variable per axis; ``c = (kp, kv, ki, h)``)."""
    (s,) = x
    e = ka * p - sp - sd
    z = ka * v - sv
    return (sa - c[0] * e - c[1] * z - c[2] * s) / ka, e, z, (s + c[3] * e,)


class PIConsensus(FormationLaw):
    """A law with one state variable per axis, as an integrator has: the engines' state of any size."""

    name = "pi"
    state = ("integral",)
    Params = PIParams
    step = staticmethod(pi_step)

    def initial(self, params: PIParams, dim: int) -> tuple[tuple[float, ...], ...]:
        return ((0.0,) * dim,)

    def coefficients(self, params: PIParams, h: float, dim: int) -> tuple[tuple[float, ...], ...]:
        return ((params.kp, params.kv, params.ki, h),) * dim


def example(duration: float = 3.0) -> ms.Mission:
    return load_mission(EXAMPLE, duration)


def assert_same(a: Run, b: Run) -> None:
    for name in SERIES:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_the_example_law_resolves_and_is_not_eq17() -> None:
    bound = laws.of_mission(example())
    assert bound.name == "pd" and bound.law.state == ()
    assert bound.coefficients(0.01) == ((2.0, 2.0), (2.0, 3.0))


@pytest.mark.parametrize(("params", "field"), [
    ("{ kp = 2.0 }", "law.params.kv"),
    ("{ kp = 2.0, kv = 1.0, kd = 3.0 }", "law.params.kd"),
    ("{ kp = -1.0, kv = 1.0 }", "law.params.kp"),
    ("{ kp = 2.0, kv = [1.0, 2.0, 3.0] }", "law.params.kv"),
    ('{ kp = "2", kv = 1.0 }', "law.params.kp"),
])
def test_check_names_the_bad_parameter(params: str, field: str) -> None:
    text = EXAMPLE.read_text().replace("params = { kp = 2.0, kv = [2.0, 3.0] }", f"params = {params}")
    with pytest.raises(ms.MissionError) as info:
        ms.loads(text)
    assert [f for f, _ in info.value.problems] == [field]


def test_check_names_a_law_that_does_not_import() -> None:
    text = EXAMPLE.read_text().replace("examples.custom_law.pd:PDConsensus", "examples.custom_law.nope:PD")
    with pytest.raises(ms.MissionError) as info:
        ms.loads(text)
    assert [f for f, _ in info.value.problems] == ["law.use"]


def test_a_builtin_kind_with_use_is_refused() -> None:
    text = EXAMPLE.read_text().replace('use = "examples', 'kind = "benchmark"\ngamma_p = 0.1\ngamma_v = 0.1\nuse = "examples')
    with pytest.raises(ms.MissionError) as info:
        ms.loads(text)
    assert "law.use" in [f for f, _ in info.value.problems]


def test_reference_numpy_and_compiled_are_equal_bit_for_bit() -> None:
    pytest.importorskip("numba")
    m = example()
    assert_same(refsim.simulate(m, engine="numpy"), refsim.simulate(m, engine="compiled"))


def test_in_process_engine_and_its_twin_equal_the_reference_bit_for_bit() -> None:
    pytest.importorskip("numba")
    m = example()
    twin = lockstep_kernel.simulate(m)
    assert twin is not None
    python = lockstep.simulate(m, engine="python")
    assert_same(twin, python)
    assert_same(python, refsim.simulate(m, engine="numpy"))
    assert np.all(python.kp == 0.0) and np.abs(python.xi).max() > 0.1  # no state; a run that moved


def test_a_law_with_one_state_variable_is_equal_in_every_engine() -> None:
    pytest.importorskip("numba")
    raw = msgspec.to_builtins(example())
    raw["law"] = {"use": "tests.test_law_custom:PIConsensus", "params": {"kp": 2.0, "kv": 2.0, "ki": 0.5}}
    m = msgspec.convert(raw, ms.Mission)
    a = refsim.simulate(m, engine="numpy")
    assert np.abs(a.kp).max() > 0.01 and np.all(a.kv == 0.0)  # the integral recorded in the first column
    assert_same(a, refsim.simulate(m, engine="compiled"))
    python = lockstep.simulate(m, engine="python")
    assert_same(a, python)
    twin = lockstep_kernel.simulate(m)
    assert twin is not None
    assert_same(python, twin)


def test_a_law_without_a_continuous_form_refuses_the_continuous_mode() -> None:
    with pytest.raises(ValueError, match="continuous-time form"):
        refsim.simulate(example(), "continuous")


SUMMED = {
    "constant + sinusoid": [{"kind": "constant", "value": [0.2, -0.1]},
                            {"kind": "sinusoid", "amplitude": [0.5, 0.6], "omega": [1.0, 2.0], "phase": [0.3, 1.1]}],
    "random + sinusoid": [{"kind": "bounded_random", "bound": 0.4, "hold": 0.05},
                          {"kind": "sinusoid", "amplitude": [0.7, 0.2], "omega": [3.0, 0.5]}],
    "constant + random + sinusoid": [{"kind": "constant", "value": [0.1, 0.3]},
                                     {"kind": "bounded_random", "bound": [0.2, 0.3], "hold": 0.1},
                                     {"kind": "sinusoid", "amplitude": [0.3, 0.9], "omega": [2.0, 4.0]}],
}


@pytest.mark.parametrize("terms", sorted(SUMMED))
@pytest.mark.parametrize("mission", ["custom", "section4"])
def test_summed_disturbances_equal_in_every_engine(terms: str, mission: str) -> None:
    """Several models summed on each agent (a held term and a sinusoid, whose increments differ in
    the last bits when added in another order): the numpy path, the compiled kernel, the in-process
    engine and its twin give the same bits, for the example law and Eq. 17."""
    pytest.importorskip("numba")
    from tether.catalog import builtin_path

    m = example(2.0) if mission == "custom" else load_mission(builtin_path("section4"), 2.0)
    raw = msgspec.to_builtins(m)
    for agent in raw["agents"]:
        agent["disturbance"] = {"kind": "sum", "terms": SUMMED[terms]}
    m2 = msgspec.convert(raw, ms.Mission)
    a = refsim.simulate(m2, engine="numpy")
    assert np.abs(a.d).max() > 0.1
    assert_same(a, refsim.simulate(m2, engine="compiled"))
    python = lockstep.simulate(m2, engine="python")
    assert_same(a, python)
    twin = lockstep_kernel.simulate(m2)
    assert twin is not None
    assert_same(python, twin)


@pytest.mark.slow  # real processes
def test_tether_run_in_lockstep_is_the_in_process_engine_bit_for_bit(tmp_path: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "cli", "run", str(EXAMPLE), "--out", str(tmp_path / "run"),
                        "--duration", "2", "--quiet"], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stderr[-3000:]
    assert_same(Run.load(tmp_path / "run"), lockstep.simulate(example(2.0)))
