"""The reference simulator against closed forms, invariants and seeded random missions."""

import math

import numpy as np
import pytest

from sim import metrics, refsim

from sim.setup import Setup
from tests.factories import one_agent, random_mission


def _closed_form_z(t: np.ndarray, z0: np.ndarray, v0: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """z'' + z' + z = d (Kp = Kv = 1), z(0) = z0, z'(0) = v0."""
    w = math.sqrt(3.0) / 2.0
    c1 = z0 - d
    c2 = (v0 + 0.5 * c1) / w
    e = np.exp(-0.5 * t)[:, None]
    cs, sn = np.cos(w * t)[:, None], np.sin(w * t)[:, None]
    z = d + e * (c1 * cs + c2 * sn)
    zd = e * (-0.5 * (c1 * cs + c2 * sn) + w * (-c1 * sn + c2 * cs))
    return z, zd


def seeds(n: int, fast: int = 2) -> list[object]:
    """Seeds ``0 .. n-1``; all but the first ``fast`` are ``slow`` (the fast lane samples each property)."""
    return [*range(fast), *(pytest.param(s, marks=pytest.mark.slow) for s in range(fast, n))]


@pytest.mark.parametrize("weight", [1.0, 2.5])
def test_continuous_mode_matches_closed_form_linear_case(weight: float) -> None:
    # Gamma tiny and K(0) = 1: gains stay 1 to ~1e-12, the loop is z'' + z' + z = d exactly
    d = np.array([0.3, -0.2])
    m = one_agent(kp0=1.0, kv0=1.0, gamma=1e-14, sigma=1.0, weight=weight, d=d.tolist(), p0=[2.0, 1.0], duration=10.0)
    run = refsim.simulate(m, "continuous", substeps=10)
    z, zd = _closed_form_z(run.t, np.array([1.0, 1.0]), np.zeros(2), d)
    np.testing.assert_allclose(run.p[:, 0] - [1.0, 0.0], z, rtol=0, atol=1e-9)
    np.testing.assert_allclose(run.v[:, 0], zd, rtol=0, atol=1e-9)
    np.testing.assert_allclose(run.kp, 1.0, rtol=0, atol=1e-10)


def test_discrete_mode_is_the_exact_zoh_recursion_and_converges_at_first_order() -> None:
    d = np.array([0.3, -0.2])
    errs = []
    for rate in (50.0, 100.0, 200.0):
        m = one_agent(kp0=1.0, kv0=1.0, gamma=1e-14, d=d.tolist(), p0=[2.0, 1.0], rate=rate, duration=10.0)
        run = refsim.simulate(m, "discrete")
        h = 1.0 / rate
        # independent recursion: z+ = z + h v + h^2/2 (u + d), v+ = v + h (u + d), u = -z - v
        z, v = np.array([1.0, 1.0]), np.zeros(2)
        zs = [z]
        for _ in range(len(run.t) - 1):
            u = -z - v
            z, v = z + h * v + 0.5 * h * h * (u + d), v + h * (u + d)
            zs.append(z)
        np.testing.assert_allclose(run.p[:, 0] - [1.0, 0.0], np.array(zs), rtol=0, atol=1e-11)
        zc, _ = _closed_form_z(run.t, np.array([1.0, 1.0]), np.zeros(2), d)
        errs.append(np.abs(run.p[:, 0] - [1.0, 0.0] - zc).max())
    assert errs[0] < 0.05
    # halving h halves the sampling error (first-order hold of the state feedback)
    assert 1.7 < errs[0] / errs[1] < 2.3 and 1.7 < errs[1] / errs[2] < 2.3


@pytest.mark.parametrize("mode", ["discrete", pytest.param("continuous", marks=pytest.mark.slow)])
def test_adaptive_equilibrium_under_constant_disturbance(mode: str) -> None:
    """With constant d the sigma law settles at xi* = kappa d / Kp*, Kv* = 1, where Kp* solves
    Kp^3 - Kp^2 - Gamma kappa^2 d^2 / sigma = 0 (per axis)."""
    d = np.array([0.4, -0.25])
    gamma, sigma, kappa = 0.2, 0.5, 1.5
    m = one_agent(kp0=1.0, kv0=1.0, gamma=gamma, sigma=sigma, weight=kappa, d=d.tolist(), duration=120.0)
    run = refsim.simulate(m, mode, substeps=2)
    kp_star = np.array([max(np.roots([1, -1, 0, -gamma * kappa**2 * x**2 / sigma]), key=lambda r: r.real).real for x in d])
    xi_star = kappa * d / kp_star
    tol = 1e-6 if mode == "continuous" else 1e-6
    np.testing.assert_allclose(run.kp[-1, 0], kp_star, rtol=0, atol=tol)
    np.testing.assert_allclose(run.xi[-1, 0], xi_star, rtol=0, atol=tol)
    np.testing.assert_allclose(run.kv[-1, 0], 1.0, rtol=0, atol=tol)


def test_equilibrium_is_a_fixed_point_of_the_discrete_map() -> None:
    d = np.array([0.4, -0.25])
    gamma, sigma = 0.2, 0.5
    kp_star = [max(np.roots([1, -1, 0, -gamma * x**2 / sigma]), key=lambda r: r.real).real for x in d]
    xi_star = d / np.array(kp_star)
    # one axis at a time (kp0 is per axis); start exactly at the equilibrium
    for axis in range(2):
        dd = [0.0, 0.0]
        dd[axis] = float(d[axis])
        p0 = [1.0, 0.0]
        p0[axis] += float(xi_star[axis])
        kp0 = [1.0, 1.0]
        kp0[axis] = float(kp_star[axis])
        m = one_agent(kp0=kp0, gamma=gamma, sigma=sigma, d=dd, p0=p0, duration=5.0)
        run = refsim.simulate(m, "discrete")
        np.testing.assert_allclose(run.p[:, 0], np.broadcast_to(p0, run.p[:, 0].shape), rtol=0, atol=1e-12)
        np.testing.assert_allclose(run.kp[:, 0, axis], kp_star[axis], rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed", range(12))
def test_sigma_law_gains_stay_at_least_one_and_within_the_invariant_bound(seed: int) -> None:
    rng = np.random.default_rng(seed)
    m = random_mission(rng, int(rng.integers(2, 9)), disturbance=["bounded_random", "sinusoid"][seed % 2],
                       duration=40.0)
    run = refsim.simulate(m, "discrete")
    assert np.all(run.kp >= 1.0) and np.all(run.kv >= 1.0)
    # exact-update invariant: K(t) <= max(K(0), 1 + Gamma max_{s<t} e(s)^2 / sigma)
    law = m.law
    for k, e, g in ((run.kp, run.xi, law.gamma_p), (run.kv, run.zeta, law.gamma_v)):
        peak_e2 = np.maximum.accumulate(e * e, axis=0)
        bound = np.maximum(k[0], 1.0 + g * peak_e2 / law.sigma)
        assert np.all(k[1:] <= bound[:-1] + 1e-12)


@pytest.mark.parametrize("seed", seeds(8))
def test_formation_is_reached_without_disturbance(seed: int) -> None:
    rng = np.random.default_rng(1000 + seed)
    profile = {"kind": "velocity_schedule", "ramp": 2.0,
               "segments": [{"t": 0.0, "v": [0.0, 0.0]}, {"t": 5.0, "v": [0.3, -0.2]}, {"t": 30.0, "v": [0.0, 0.1]}]}
    m = random_mission(rng, int(rng.integers(2, 7)), duration=120.0, profile=profile)
    run = refsim.simulate(m, "discrete")
    offsets = Setup.of(m).offsets[: m.n]
    err = np.linalg.norm(run.p[-1] - offsets - run.leader_p[-1], axis=1)
    assert err.max() < 1e-3, err
    np.testing.assert_allclose(run.v[-1], np.broadcast_to(run.leader_v[-1], run.v[-1].shape), rtol=0, atol=1e-3)


@pytest.mark.parametrize("seed", seeds(8))
def test_ultimate_boundedness_under_bounded_disturbance(seed: int) -> None:
    rng = np.random.default_rng(2000 + seed)
    m = random_mission(rng, int(rng.integers(2, 7)), disturbance="bounded_random", d0=0.5, duration=200.0)
    run = refsim.simulate(m, "discrete")
    xn = metrics.xi_norm(run)
    q = len(run.t) // 4
    assert np.all(np.isfinite(run.xi))
    # no growth: the RMS error of the last quarter is not above the second quarter's
    rms_mid, rms_last = np.sqrt(np.mean(xn[q : 2 * q] ** 2)), np.sqrt(np.mean(xn[3 * q :] ** 2))
    assert rms_last <= 1.5 * rms_mid + 0.01, (rms_mid, rms_last)
    # and bounded in absolute terms: ||d_hat_i|| <= kappa_i d0 drives a loop whose gains are >= 1
    kappa_max = Setup.of(m).topo.kappa.max()
    assert xn[2 * q :].max() <= 10.0 * kappa_max * 0.5
    assert metrics.growth_rate(run.t, run.kp) < 1e-3


@pytest.mark.parametrize("seed", range(6))
def test_benchmark_gains_never_decrease(seed: int) -> None:
    rng = np.random.default_rng(3000 + seed)
    m = random_mission(rng, int(rng.integers(2, 7)), law="benchmark", disturbance="sinusoid", duration=40.0)
    run = refsim.simulate(m, "discrete")
    assert np.all(np.diff(run.kp, axis=0) >= 0.0)
    assert np.all(np.diff(run.kv, axis=0) >= 0.0)


def test_discrete_converges_to_continuous_on_section4() -> None:
    import msgspec

    from tether.catalog import builtin_path
    from tether import mission

    m = mission.load(builtin_path("section4"))
    ref = refsim.simulate(m, "continuous", duration=4.0, substeps=10)
    errs = []
    for rate in (100.0, 400.0):
        r = refsim.simulate(msgspec.structs.replace(m, rate=rate), "discrete", duration=4.0)
        errs.append(np.abs(r.xi[:: int(rate // 100)] - ref.xi).max())
    assert errs[1] < errs[0] / 3.0


def test_unrecorded_run_keeps_only_the_final_sample() -> None:
    m = random_mission(np.random.default_rng(9), 5, disturbance="sinusoid", duration=3.0)
    full = refsim.simulate(m, "discrete")
    last = refsim.simulate(m, "discrete", record=False)
    assert last.t.shape == (1,)
    np.testing.assert_array_equal(last.p[0], full.p[-1])
    np.testing.assert_array_equal(last.kp[0], full.kp[-1])
