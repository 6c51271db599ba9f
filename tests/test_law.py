"""The laws as pure functions: the exact gain step, single-agent vs all-agent forms, the contract."""

import math

import numpy as np
import pytest

from agent import law, laws
from agent.laws import sigma as eq17
from sim import refsim
from sim.setup import Setup
from tests.factories import random_mission


def _gain_step(k: np.ndarray, e: np.ndarray, gamma: float, s: float, h: float) -> np.ndarray:
    """Eq. 17's gain update through its step: Kp's next value for errors ``e`` (zeta 0)."""
    decay, gain = eq17.gain_coefficients(s, h)
    one = np.ones_like(k)
    _, _, _, (kp, _) = eq17.step(one, e, 0.0 * e, 0.0 * e, 0.0 * e, 0.0 * e, 0.0 * e, (k, one),
                                 (decay, gamma * gain, gamma * gain))
    return kp


def test_gain_step_is_the_exact_solution_of_the_gain_ode() -> None:
    # K' = -sigma (K - 1) + Gamma e^2 with e held: K(h) = 1 + (K0-1) e^{-sigma h} + Gamma e^2 (1 - e^{-sigma h}) / sigma
    sigma, gamma, h, k0, e = 0.7, 0.3, 0.05, np.array([1.4, 3.0]), np.array([0.5, -2.0])
    got = _gain_step(k0, e, gamma, sigma, h)
    # independent check: fine RK4 on the ODE
    k, n = k0.copy(), 20000
    dt = h / n
    for _ in range(n):
        f = lambda kk: -sigma * (kk - 1) + gamma * e * e  # noqa: E731
        k1 = f(k); k2 = f(k + dt / 2 * k1); k3 = f(k + dt / 2 * k2); k4 = f(k + dt * k3)  # noqa: E702
        k = k + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    np.testing.assert_allclose(got, k, rtol=0, atol=1e-12)


def test_benchmark_gain_step_is_euler_exact() -> None:
    assert eq17.gain_coefficients(0.0, 0.01) == (1.0, 0.01)
    np.testing.assert_allclose(_gain_step(np.array([0.2]), np.array([3.0]), 0.5, 0.0, 0.01), [0.2 + 0.5 * 9 * 0.01],
                               rtol=0, atol=1e-15)


@pytest.mark.parametrize("seed", range(50))
def test_gain_step_keeps_k_at_least_one(seed: int) -> None:
    rng = np.random.default_rng(seed)
    sigma = float(rng.uniform(1e-3, 50))
    h = float(rng.uniform(1e-4, 1.0))
    k = 1.0 + rng.exponential(1.0, 3) * rng.integers(0, 2, 3)  # some exactly 1
    e = rng.normal(0, 10, 3) * rng.integers(0, 2, 3)  # some exactly 0
    for _ in range(200):
        k = _gain_step(k, e, 0.1, sigma, h)
        assert np.all(k >= 1.0)
        e = e * 0.5


@pytest.mark.parametrize("seed", range(12))
def test_single_agent_and_all_agent_forms_agree_bit_for_bit(seed: int) -> None:
    """One agent's law (the agent process, the in-process engine) against every agent's at once
    (the reference simulator): identical, whatever the in-degree and the weights. The dense
    missions give every agent 3 to 12 in-neighbours with weights that do not multiply exactly,
    where a BLAS product's fused multiply-adds (4 terms on) and a pairwise kappa (8 on) differed."""
    rng = np.random.default_rng(100 + seed)
    m = random_mission(rng, int(rng.integers(2, 15)) if seed < 6 else int(rng.integers(3, 13)), dim=3,
                       dense=seed >= 6)
    s = Setup.of(m)
    n, d = m.n, m.dim
    x = rng.normal(0, 3, (n + 1, 3, d))  # p, v, a of every node, leader last
    kp = rng.uniform(1, 5, (n, d))
    kv = rng.uniform(1, 5, (n, d))
    sums = refsim.neighbour_sums(s.topo, x.reshape(n + 1, 3 * d)).reshape(n, 3, d)
    kappa = s.topo.kappa[:, None]
    coef = tuple(np.array(col) for col in zip(*s.bound.coefficients(m.dt)))
    u, xi, zeta, (kp1, kv1) = s.bound.law.step(kappa, x[:n, 0], x[:n, 1], sums[:, 0], sums[:, 1], sums[:, 2],
                                               s.sum_wdelta, (kp, kv), coef)
    for i, a in enumerate(m.agents):
        al = law.AgentLaw.from_mission(m, a.id)
        rows = [m.index_of(j) for j in al.neighbours]
        assert al.kappa == s.topo.kappa[i]
        np.testing.assert_array_equal(al.sum_wdelta, s.sum_wdelta[i])
        for arg in (lambda z: z, lambda z: z.tolist()):  # numpy rows and Python floats
            ui, xii, zetai, kpi, kvi = al.step(arg(x[i, 0]), arg(x[i, 1]), arg(x[rows, 0]), arg(x[rows, 1]),
                                                 arg(x[rows, 2]), arg(kp[i]), arg(kv[i]))
            np.testing.assert_array_equal(ui, u[i])
            np.testing.assert_array_equal(xii, xi[i])
            np.testing.assert_array_equal(zetai, zeta[i])
            np.testing.assert_array_equal(kpi, kp1[i])
            np.testing.assert_array_equal(kvi, kv1[i])


def test_errors_match_the_paper_definition() -> None:
    """xi_i = sum_j a_ij (p_i - p_j - delta_ij) computed literally, against the kappa form."""
    rng = np.random.default_rng(5)
    m = random_mission(rng, 6)
    s = Setup.of(m)
    n = m.n
    p = rng.normal(0, 2, (n + 1, m.dim))
    h = s.offsets
    a = s.topo.adjacency
    literal = np.array([sum(a[i, j] * (p[i] - p[j] - (h[i] - h[j])) for j in range(n + 1)) for i in range(n)])
    sp = refsim.neighbour_sums(s.topo, p)
    one = np.ones_like(p[:n])
    _, xi, _, _ = eq17.step(s.topo.kappa[:, None], p[:n], p[:n], sp, sp, sp, s.sum_wdelta, (one, one),
                            (1.0, 0.0, 0.0))
    np.testing.assert_allclose(xi, literal, rtol=0, atol=1e-12)


def test_gain_step_sigma_limit() -> None:
    a = eq17.gain_coefficients(1e-12, 0.01)
    b = eq17.gain_coefficients(0.0, 0.01)
    assert math.isclose(a[1], b[1], rel_tol=1e-9)


def test_builtin_and_imported_laws_resolve() -> None:
    assert laws.resolve("sigma").name == "sigma"
    assert laws.resolve("benchmark").name == "benchmark"
    assert type(laws.resolve("agent.laws.sigma:Sigma")) is eq17.Sigma
    for bad, why in (("nonsense", "package.module:Class"), ("no_such_module_xyz:Law", "does not import"),
                     ("agent.laws.sigma:step", "FormationLaw subclass")):
        with pytest.raises(laws.LawNotFound, match=why):
            laws.resolve(bad)


def test_per_axis_rates_reach_the_coefficients() -> None:
    """Eq. 30's diag(Gamma_p): one adaptation rate per axis."""
    law_ = laws.resolve("benchmark")
    prm = law_.Params(kp0=1.0, kv0=[1.0, 2.0], gamma_p=[0.1, 0.2], gamma_v=0.3)
    assert law_.check(prm, 2) == []
    assert law_.coefficients(prm, 0.01, 2) == ((1.0, 0.1 * 0.01, 0.3 * 0.01), (1.0, 0.2 * 0.01, 0.3 * 0.01))
    assert [f for f, _ in law_.check(law_.Params(kp0=1.0, kv0=1.0, gamma_p=[0.1, -1.0], gamma_v=0.3), 2)] \
        == ["gamma_p[1]"]
