"""Mission schema: a disturbance may be a sum of models, evaluated exactly as the single models
are; a velocity schedule may hold before its first ramp. Checked in the reference simulator."""

from __future__ import annotations

import numpy as np
import pytest

from plant.disturbance import DisturbanceBank
from sim import refsim
from tether import mission as ms

BASE = """
version = 1
name = "sum"
dim = 2
rate = 50.0
duration = 6.0
seed = 3
edges = [ {{ from = 3, to = 1 }}, {{ from = 1, to = 2 }}, {{ from = 2, to = 1 }} ]
[law]
kind = "sigma"
kp0 = 1.5
kv0 = 1.2
gamma_p = 0.1
gamma_v = 0.05
sigma = 0.1
[leader]
id = 3
p0 = [0.0, 0.0]
profile = {{ kind = "velocity_schedule", ramp = 3.0, segments = [ {{ t = 0.0, v = [0.0, 0.0] }}, {{ t = 2.0, v = [0.3, -0.1] }} ] }}
[[agents]]
id = 1
p0 = [0.5, 0.2]
offset = [0.5, 0.0]
{dist1}
[[agents]]
id = 2
p0 = [-0.5, 0.1]
offset = [-0.5, 0.0]
{dist2}
"""

CONST = 'kind = "constant"\nvalue = [0.05, -0.02]\n'
SINE = 'kind = "sinusoid"\namplitude = [0.1, 0.1]\nomega = [1.0, 2.0]\nphase = [0.3, 0.0]\n'
SINE2 = 'kind = "sinusoid"\namplitude = [0.04, 0.0]\nomega = [5.0, 1.0]\n'
RAND = 'kind = "bounded_random"\nbound = 0.08\nhold = 0.2\n'


def single(body: str) -> str:
    return "[agents.disturbance]\n" + body


def summed(*bodies: str) -> str:
    return '[agents.disturbance]\nkind = "sum"\n' + "".join("[[agents.disturbance.terms]]\n" + b for b in bodies)


def mission(dist1: str = "", dist2: str = "") -> ms.Mission:
    return ms.loads(BASE.format(dist1=dist1, dist2=dist2))


def test_a_sum_reads_as_a_list_of_tables() -> None:
    m = mission(summed(CONST, SINE))
    d = m.agent(1).disturbance
    assert isinstance(d, ms.DisturbanceSum)
    assert [type(t) for t in d.terms] == [ms.Constant, ms.Sinusoid]


@pytest.mark.parametrize("parts", [(CONST, SINE), (SINE, SINE2), (CONST, SINE, RAND)])
def test_summed_disturbance_is_the_sum_of_its_parts_bit_for_bit(parts: tuple[str, ...]) -> None:
    """The disturbance the reference simulator applies (recorded d, and the exact increments the
    plant integrates) for the summed mission equals the sum of the parts' own runs, bit for bit:
    each part is computed by the same expression as alone, and the parts are added in term order
    (for two parts that is one addition, the same one; for three, the same left-to-right order)."""
    whole = refsim.simulate(mission(summed(*parts), single(SINE2)))
    runs = [refsim.simulate(mission(single(p), single(SINE2))) for p in parts]
    total = runs[0].d[:, 0]
    for r in runs[1:]:
        total = total + r.d[:, 0]
    if parts == (CONST, SINE, RAND):
        # the bank adds const + sines + randoms: a different order of the same three numbers
        np.testing.assert_allclose(whole.d[:, 0], total, rtol=0, atol=1e-15)
    else:
        np.testing.assert_array_equal(whole.d[:, 0], total)
    np.testing.assert_array_equal(whole.d[:, 1], runs[0].d[:, 1])  # the other agent is untouched
    bank = DisturbanceBank.from_mission(mission(summed(*parts)))
    banks = [DisturbanceBank.from_mission(mission(single(p))) for p in parts]
    for k in (0, 1, 57, 299):
        dv, dp = bank.increments(k)
        inc = [b.increments(k) for b in banks]
        sv, sp = inc[0]
        for v, p in inc[1:]:
            sv, sp = sv + v, sp + p
        np.testing.assert_allclose(dv, sv, rtol=0, atol=1e-18)
        np.testing.assert_allclose(dp, sp, rtol=0, atol=1e-18)


def test_a_one_term_sum_flies_exactly_as_the_single_model() -> None:
    for body in (CONST, SINE, RAND):
        a = refsim.simulate(mission(summed(body)))
        b = refsim.simulate(mission(single(body)))
        for name in ("p", "v", "u", "xi", "d", "kp"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_sum_problems_name_the_term() -> None:
    with pytest.raises(ms.MissionError) as e:
        mission(summed(CONST, 'kind = "sinusoid"\namplitude = [0.1]\nomega = [1.0, 2.0]\n'))
    assert "agent 1.disturbance.terms[1].amplitude" in str(e.value)
    with pytest.raises(ms.MissionError) as e:
        mission('[agents.disturbance]\nkind = "sum"\nterms = []\n')
    assert "agent 1.disturbance.terms" in str(e.value)


def test_hold_then_ramp_is_accepted_and_flown_exactly() -> None:
    """Hold 2 s at rest, then ramp for 3 s to (0.3, -0.1) m/s: the leader's recorded velocity and
    position at every sample time are the closed form."""
    r = refsim.simulate(mission())
    t = r.t
    vt = np.array([0.3, -0.1])
    s = np.clip((t - 2.0) / 3.0, 0.0, 1.0)
    np.testing.assert_allclose(r.leader_v, s[:, None] * vt, rtol=0, atol=1e-12)
    ramp = np.clip(t - 2.0, 0.0, 3.0)
    dist = ramp**2 / 6.0 + np.clip(t - 5.0, 0.0, None) * 1.0  # integral of s(t)
    np.testing.assert_allclose(r.leader_p, dist[:, None] * vt, rtol=0, atol=1e-12)
    ramping = r.leader_a[(t > 2.01) & (t < 4.99)]
    np.testing.assert_allclose(ramping, np.broadcast_to(vt / 3.0, ramping.shape), rtol=0, atol=1e-12)


def test_a_later_ramp_still_may_not_start_before_the_previous_ends() -> None:
    text = BASE.format(dist1="", dist2="").replace(
        '{ t = 2.0, v = [0.3, -0.1] } ]', '{ t = 2.0, v = [0.3, -0.1] }, { t = 4.0, v = [0.0, 0.0] } ]')
    with pytest.raises(ms.MissionError) as e:
        ms.loads(text)
    assert "leader.profile.segments[2].t" in str(e.value) and "5.0 s" in str(e.value)


MIXED = [("none", ""), ("constant", single(CONST)), ("sinusoid", single(SINE)), ("random", single(RAND)),
         ("sum of two sinusoids", summed(SINE, SINE2)), ("constant + sinusoid + random", summed(CONST, SINE, RAND)),
         ("two randoms", summed(RAND, CONST, RAND))]


@pytest.mark.parametrize("name,body", MIXED, ids=[n for n, _ in MIXED])
@pytest.mark.parametrize("rows", ["one vehicle", "both"])
def test_the_banks_blocks_of_ticks_are_its_one_tick_arithmetic_bit_for_bit(name: str, body: str, rows: str) -> None:
    """``value`` and ``increments`` hand out rows of a block of ticks computed at once: every number
    (sign of zero included) is the one ``value_of`` and ``increments_of`` compute for that tick
    alone, across block edges, after a jump (a restarted plant's ``seek``) and back, and the rows
    cannot be written (a caller changing one would change every later reader's disturbance)."""
    from plant import disturbance as dm

    m = mission(body, single(SINE2))
    bank = DisturbanceBank.from_mission(m, [1] if rows == "one vehicle" else None)
    per_block = min(dm.CACHE_TICKS, dm.CACHE_NUMBERS // max(1, bank.amp.size, bank.const.size))
    ticks = [*range(0, 2 * per_block + 3), 5 * per_block + 7, 3, per_block - 1, per_block]
    for k in ticks:
        for got, want in zip((bank.value(k), *bank.increments(k)), (bank.value_of(k), *bank.increments_of(k))):
            assert got.shape == want.shape and got.dtype == want.dtype
            assert got.tobytes() == want.tobytes(), (name, k)
    with pytest.raises(ValueError):
        bank.value(0)[0, 0] = 1.0
    with pytest.raises(ValueError):
        bank.increments(0)[0][0, 0] = 1.0
