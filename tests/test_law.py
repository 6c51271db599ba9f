"""The laws as pure functions: shapes, the exact gain step, single-agent vs all-agent forms."""

import math

import numpy as np
import pytest

from agent import law
from sim import refsim
from tests.factories import random_mission


def test_gain_step_is_the_exact_solution_of_the_gain_ode() -> None:
    # K' = -sigma (K - 1) + Gamma e^2 with e held: K(h) = 1 + (K0-1) e^{-sigma h} + Gamma e^2 (1 - e^{-sigma h}) / sigma
    sigma, gamma, h, k0, e = 0.7, 0.3, 0.05, np.array([1.4, 3.0]), np.array([0.5, -2.0])
    step = law.GainStep.over(sigma, h)
    got = law.gain_update(k0, e, gamma, step)
    # independent check: fine RK4 on the ODE
    k, n = k0.copy(), 20000
    dt = h / n
    for _ in range(n):
        f = lambda kk: -sigma * (kk - 1) + gamma * e * e  # noqa: E731
        k1 = f(k); k2 = f(k + dt / 2 * k1); k3 = f(k + dt / 2 * k2); k4 = f(k + dt * k3)  # noqa: E702
        k = k + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    np.testing.assert_allclose(got, k, rtol=0, atol=1e-12)


def test_benchmark_gain_step_is_euler_exact() -> None:
    step = law.GainStep.over(0.0, 0.01)
    assert step.decay == 1.0 and step.gain == 0.01
    np.testing.assert_allclose(law.gain_update(np.array([0.2]), np.array([3.0]), 0.5, step), [0.2 + 0.5 * 9 * 0.01],
                               rtol=0, atol=1e-15)


@pytest.mark.parametrize("seed", range(50))
def test_gain_step_keeps_k_at_least_one(seed: int) -> None:
    rng = np.random.default_rng(seed)
    sigma = float(rng.uniform(1e-3, 50))
    h = float(rng.uniform(1e-4, 1.0))
    k = 1.0 + rng.exponential(1.0, 3) * rng.integers(0, 2, 3)  # some exactly 1
    e = rng.normal(0, 10, 3) * rng.integers(0, 2, 3)  # some exactly 0
    step = law.GainStep.over(sigma, h)
    for _ in range(200):
        k = law.gain_update(k, e, 0.1, step)
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
    s = refsim.Setup.of(m)
    n, d = m.n, m.dim
    x = rng.normal(0, 3, (n + 1, 3, d))  # p, v, a of every node, leader last
    kp = rng.uniform(1, 5, (n, d))
    kv = rng.uniform(1, 5, (n, d))
    sums = refsim.neighbour_sums(s.topo, x.reshape(n + 1, 3 * d)).reshape(n, 3, d)
    kappa = s.topo.kappa[:, None]
    xi, zeta = law.errors(kappa, x[:n, 0], x[:n, 1], sums[:, 0], sums[:, 1], s.sum_wdelta)
    u = law.control(kappa, sums[:, 2], xi, zeta, kp, kv)
    gs = law.GainStep.over(s.params.sigma, m.dt)
    kp1 = law.gain_update(kp, xi, s.params.gamma_p, gs)
    for i, a in enumerate(m.agents):
        al = law.AgentLaw.from_mission(m, a.id)
        rows = [m.index_of(j) for j in al.neighbours]
        assert al.kappa == s.topo.kappa[i]
        np.testing.assert_array_equal(al.sum_wdelta, s.sum_wdelta[i])
        for step in (al.step, al.step_numpy):
            ui, xii, zetai, kpi, _ = step(x[i, 0], x[i, 1], x[rows, 0], x[rows, 1], x[rows, 2], kp[i], kv[i])
            np.testing.assert_array_equal(ui, u[i])
            np.testing.assert_array_equal(xii, xi[i])
            np.testing.assert_array_equal(zetai, zeta[i])
            np.testing.assert_array_equal(kpi, kp1[i])



@pytest.mark.parametrize("seed", range(8))
def test_step_on_floats_equals_its_vectorised_form_bit_for_bit(seed: int) -> None:
    """AgentLaw.step (term by term on Python floats, the hot path) against step_numpy (the same law
    written with errors(), control() and gain_update()): every output identical, not merely close."""
    rng = np.random.default_rng(100 + seed)
    m = random_mission(rng, int(rng.integers(2, 7)))
    for a in m.agents:
        al = law.AgentLaw.from_mission(m, a.id)
        k = len(al.neighbours)
        p, v = rng.normal(0, 3, m.dim), rng.normal(0, 3, m.dim)
        nb = rng.normal(0, 3, (3, k, m.dim))
        kp, kv = rng.uniform(1, 5, m.dim), rng.uniform(1, 5, m.dim)
        fast = al.step(p, v, nb[0], nb[1], nb[2], kp, kv)
        ref = al.step_numpy(p, v, nb[0], nb[1], nb[2], kp, kv)
        for got, want in zip(fast, ref):
            assert np.array_equal(got, want), (got, want)

def test_errors_match_the_paper_definition() -> None:
    """xi_i = sum_j a_ij (p_i - p_j - delta_ij) computed literally, against the kappa form."""
    rng = np.random.default_rng(5)
    m = random_mission(rng, 6)
    s = refsim.Setup.of(m)
    n = m.n
    p = rng.normal(0, 2, (n + 1, m.dim))
    h = s.offsets
    a = s.topo.adjacency
    literal = np.array([sum(a[i, j] * (p[i] - p[j] - (h[i] - h[j])) for j in range(n + 1)) for i in range(n)])
    sp = refsim.neighbour_sums(s.topo, p)
    xi, _ = law.errors(s.topo.kappa[:, None], p[:n], p[:n], sp, sp, s.sum_wdelta)
    np.testing.assert_allclose(xi, literal, rtol=0, atol=1e-12)


def test_gain_step_sigma_limit() -> None:
    a = law.GainStep.over(1e-12, 0.01)
    b = law.GainStep.over(0.0, 0.01)
    assert math.isclose(a.gain, b.gain, rel_tol=1e-9)
