"""The message-level network emulator (``netem``): statistics of every impairment against its
closed form, the exact cases (identity, rate, outages, gap), determinism, validation and presets.

Statistical checks use a bound of ``Z = 5`` standard deviations of the estimator, computed from the
model's own closed form (binomial counts, Markov-chain and AR(1) variance factors, Bartlett's
variance of a lag-1 autocorrelation): under the normal approximation a correct implementation
fails one check with probability below 6e-7 for a random seed. Where the estimator is too
heavy-tailed for the normal approximation (the Pareto mean), Chebyshev's inequality is used
instead, at the confidence stated there. Seeds are fixed, so the tests are deterministic.
"""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import numpy as np
import pytest

from netem.channel import DROP_REASONS, Decision, Delivery, DeliveryQueue, Link, link_rng
from tether.netprofile import (
    IDENTITY, PRESET_NOTES, PRESETS, Bernoulli, Corrupt, Delay, GilbertElliott, LinkProfile,
    LinkRule, Network, ProfileError, Rate, Reorder, convert, is_identity, mean_loss, preset,
    profile_at, schedule, validate, validate_network,
)

Z = 5.0
"""Width of every statistical bound, in standard deviations of the estimator."""

DOC = Path(__file__).parent.parent / "docs" / "netem.md"
PAYLOAD = bytes(range(100))


def _run(profile: LinkProfile, n: int, dt: float = 0.01, seed: int = 1,
         payload: bytes = PAYLOAD) -> tuple[Link, list[list[Delivery]]]:
    """Offer ``n`` messages every ``dt`` seconds from t = 0 on a fresh link."""
    link = Link(profile, link_rng(seed, 1, 2))
    return link, [link.offer(k * dt, payload) for k in range(n)]


def _within(x: float, mean: float, std: float, z: float = Z) -> bool:
    return abs(x - mean) <= z * std


def _binomial_ok(k: int, n: int, p: float) -> bool:
    return _within(k, n * p, math.sqrt(n * p * (1 - p)))


def _runs(flags: np.ndarray, value: bool) -> np.ndarray:
    """Lengths of the maximal runs of ``value`` in a boolean array (runs cut by either end left out)."""
    x = np.concatenate(([0], (flags == value).astype(np.int8), [0]))
    edges = np.flatnonzero(np.diff(x))
    starts, ends = edges[::2], edges[1::2]
    lengths = ends - starts
    inner = (starts > 0) & (ends < len(flags))
    return lengths[inner]


def _lag1(x: np.ndarray) -> float:
    x = x - x.mean()
    return float(np.dot(x[1:], x[:-1]) / np.dot(x, x))


# --------------------------------------------------------------------------- identity
def test_identity_returns_the_payload_at_now_and_draws_nothing():
    rng = link_rng(7, 1, 2)
    before = rng.bit_generator.state
    link = Link(LinkProfile(), rng, log=True)
    times = np.cumsum(np.random.default_rng(0).exponential(0.01, 2000))
    payloads = [bytes([k % 256]) * (k % 37) for k in range(len(times))]
    queue = DeliveryQueue()
    for t, p in zip(times.tolist(), payloads, strict=True):
        out = link.offer(t, p)
        assert out == [Delivery(t, p, "deliver")]
        assert out[0].at == t and out[0].payload is p
        queue.push(out)
        assert [d.payload for d in queue.pop_due(t)] == [p]  # held for no time at all
    assert rng.bit_generator.state == before
    assert link.counts["offered"] == link.counts["delivered"] == len(times)
    assert link.last_drop_reason is None
    assert [d.event for d in link.take_decisions()] == ["deliver"] * len(times)


def test_identity_leaves_every_stream_untouched():
    """A link that was the identity for a while then switches to a profile exercising every random
    stream decides exactly as a link created with that profile at the switch: nothing was drawn."""
    busy = LinkProfile(delay=Delay(constant=0.01, jitter=0.005, distribution="normal", correlation=0.5),
                       loss=GilbertElliott(p=0.1, r=0.3, bad_loss=0.7, good_loss=0.05), duplicate=0.2,
                       reorder=Reorder(p=0.2, gap=1), corrupt=Corrupt(p=0.2, bytes=2))
    a = Link(IDENTITY, link_rng(3, 4, 5))
    for k in range(500):
        a.offer(k * 0.01, PAYLOAD)
    a.set_profile(busy)
    b = Link(busy, link_rng(3, 4, 5))
    for k in range(500, 2500):
        assert a.offer(k * 0.01, PAYLOAD) == b.offer(k * 0.01, PAYLOAD)


def test_is_identity():
    assert is_identity(LinkProfile()) and is_identity(PRESETS["ideal"])
    assert is_identity(LinkProfile(loss=GilbertElliott(p=0.0, r=0.5, bad_loss=1.0)))
    assert not is_identity(LinkProfile(loss=GilbertElliott(p=0.0, good_loss=0.1)))
    assert not is_identity(LinkProfile(outages=((1.0, 2.0),)))
    assert not is_identity(LinkProfile(rate=Rate(bytes_per_s=1e6)))


# --------------------------------------------------------------------------- loss
def test_bernoulli_loss_ratio():
    n, p = 20_000, 0.1
    link = Link(LinkProfile(loss=Bernoulli(p=p)), link_rng(1, 1, 2))
    lost = 0
    for k in range(n):
        if not link.offer(k * 0.01, PAYLOAD):
            lost += 1
            assert link.last_drop_reason == "loss"
    assert _binomial_ok(lost, n, p), lost
    assert link.counts["loss"] == lost


def test_gilbert_elliott_bursts_gaps_and_stationary_loss():
    """bad_loss = 1, good_loss = 0: loss runs are the bad sojourns, Geometric(r) of mean 1/r, and
    delivery runs the good sojourns, of mean 1/p; the loss fraction is pi_B = p/(p+r)."""
    n, p, r = 60_000, 0.05, 0.25
    _, outs = _run(LinkProfile(loss=GilbertElliott(p=p, r=r)), n)
    lost = np.array([not o for o in outs])
    bursts, gaps = _runs(lost, True), _runs(lost, False)
    # Geometric(q) sojourns: mean 1/q, variance (1-q)/q^2
    assert _within(bursts.mean(), 1 / r, math.sqrt((1 - r) / r**2 / len(bursts))), bursts.mean()
    assert _within(gaps.mean(), 1 / p, math.sqrt((1 - p) / p**2 / len(gaps))), gaps.mean()
    # a two-state chain's occupation fraction: variance pi(1-pi)(1+lam)/(1-lam)/n, lam = 1-p-r
    pi_b, lam = p / (p + r), 1 - p - r
    assert _within(lost.mean(), pi_b, math.sqrt(pi_b * (1 - pi_b) * (1 + lam) / (1 - lam) / n)), lost.mean()


def test_gilbert_elliott_with_losses_in_both_states():
    n, p, r, hb, hg = 60_000, 0.02, 0.1, 0.6, 0.01
    model = GilbertElliott(p=p, r=r, bad_loss=hb, good_loss=hg)
    _, outs = _run(LinkProfile(loss=model), n)
    lost = np.array([not o for o in outs])
    pi_b, lam = p / (p + r), 1 - p - r
    expected = pi_b * hb + (1 - pi_b) * hg
    assert mean_loss(model) == pytest.approx(expected, rel=1e-12)
    # Var(sum L) = sum E[q(1-q)] + Var(sum q(S_n)), the second a chain occupation variance
    var = (pi_b * hb * (1 - hb) + (1 - pi_b) * hg * (1 - hg)
           + (hb - hg) ** 2 * pi_b * (1 - pi_b) * (1 + lam) / (1 - lam)) / n
    assert _within(lost.mean(), expected, math.sqrt(var)), lost.mean()


def test_gilbert_elliott_r_defaults_to_one_minus_p():
    """With r = 1 - p the next state does not depend on the current one: i.i.d. losses of rate p."""
    n, p = 20_000, 0.2
    _, outs = _run(LinkProfile(loss=GilbertElliott(p=p)), n)
    lost = np.array([not o for o in outs], dtype=float)
    assert _binomial_ok(int(lost.sum()), n, p)
    assert _within(_lag1(lost), 0.0, 1 / math.sqrt(n))


# --------------------------------------------------------------------------- delay
def _delays(delay: Delay, n: int, dt: float = 1.0) -> np.ndarray:
    _, outs = _run(LinkProfile(delay=delay), n, dt=dt)
    return np.array([o[0].at - k * dt for k, o in enumerate(outs)])


def test_uniform_jitter_moments_and_range():
    n, c, j = 20_000, 0.1, 0.02
    d = _delays(Delay(constant=c, jitter=j), n)
    sigma = j / math.sqrt(3)
    assert d.min() >= c - j - 1e-12 and d.max() <= c + j + 1e-12
    assert _within(d.mean(), c, sigma / math.sqrt(n))
    # sample std: relative standard error sqrt((kurtosis - 1) / 4n), kurtosis 9/5 for a uniform
    assert _within(d.std() / sigma, 1.0, math.sqrt(0.8 / (4 * n)))


def test_normal_jitter_moments():
    n, c, j = 20_000, 1.0, 0.05
    d = _delays(Delay(constant=c, jitter=j, distribution="normal"), n)
    assert _within(d.mean(), c, j / math.sqrt(n))
    assert _within(d.std() / j, 1.0, math.sqrt(2 / (4 * n)))
    assert _within(_lag1(d), 0.0, 1 / math.sqrt(n))


@pytest.mark.parametrize("rho", [0.3, 0.8])
def test_normal_jitter_correlation_is_the_lag1_autocorrelation(rho):
    """The delays are a Gaussian AR(1): lag-1 autocorrelation rho (Bartlett: variance (1-rho^2)/n),
    with the marginal unchanged (unlike netem's mixing, which shrinks the variance)."""
    n, c, j = 20_000, 1.0, 0.05
    d = _delays(Delay(constant=c, jitter=j, distribution="normal", correlation=rho), n)
    assert _within(_lag1(d), rho, math.sqrt((1 - rho**2) / n)), _lag1(d)
    assert _within(d.mean(), c, j * math.sqrt((1 + rho) / (1 - rho) / n))
    # AR(1) sample variance: variance 2 sigma^4 (1+rho^2)/(1-rho^2)/n; for the std, half the relative error
    assert _within(d.std() / j, 1.0, 0.5 * math.sqrt(2 * (1 + rho**2) / (1 - rho**2) / n))


def test_uniform_jitter_correlation_keeps_the_marginal():
    """Through the Gaussian copula the lag-1 correlation of uniform jitter is (6/pi) asin(rho/2)
    (Spearman's rho of the copula), and the marginal stays uniform on [c - j, c + j]. The bound uses
    Bartlett's Gaussian variance, which is close here (not exact for a non-Gaussian series)."""
    n, c, j, rho = 20_000, 0.1, 0.02, 0.6
    d = _delays(Delay(constant=c, jitter=j, correlation=rho), n)
    expected = 6 / math.pi * math.asin(rho / 2)
    assert _within(_lag1(d), expected, math.sqrt((1 - expected**2) / n)), _lag1(d)
    assert d.min() >= c - j - 1e-12 and d.max() <= c + j + 1e-12
    counts, _ = np.histogram(d, bins=10, range=(c - j, c + j))
    # bin counts of a correlated series: binomial variance inflated by at most (1+rho)/(1-rho)
    inflate = (1 + rho) / (1 - rho)
    assert all(_within(k, n / 10, math.sqrt(n * 0.1 * 0.9 * inflate)) for k in counts), counts


def test_pareto_jitter_bound_and_tail():
    """Z = (X - 3/2) / (sqrt(3)/2) with X Pareto of shape 3 and scale 1: mean 0, standard deviation
    1, Z >= -1/sqrt(3), and P(Z > z) = (3/2 + z sqrt(3)/2)^-3."""
    n, c, j = 50_000, 1.0, 0.1
    d = _delays(Delay(constant=c, jitter=j, distribution="pareto"), n)
    zs = (d - c) / j
    assert zs.min() >= -1 / math.sqrt(3) - 1e-9
    for z in (0.0, 1.0, 2.0, 4.0, 8.0):
        tail = (1.5 + z * math.sqrt(3) / 2) ** -3
        assert _binomial_ok(int((zs > z).sum()), n, tail), (z, (zs > z).mean(), tail)
    # the mean's estimator is heavy-tailed (infinite third moment): Chebyshev at 99.9 %
    assert _within(d.mean(), c, j / math.sqrt(n), z=math.sqrt(1000))


def test_delay_is_clamped_at_zero():
    d = _delays(Delay(constant=0.0, jitter=0.01, distribution="normal"), 2000)
    assert d.min() == 0.0
    assert _binomial_ok(int((d == 0).sum()), 2000, 0.5)


# --------------------------------------------------------------------------- duplicate, reorder, corrupt
def test_duplication_ratio():
    n, p = 20_000, 0.05
    link, outs = _run(LinkProfile(duplicate=p, delay=Delay(constant=0.02)), n)
    twice = [o for o in outs if len(o) == 2]
    assert all(len(o) in (1, 2) for o in outs)
    assert _binomial_ok(len(twice), n, p), len(twice)
    for o in twice:
        assert [d.event for d in o] == ["deliver", "duplicate"]
        assert o[0].payload == o[1].payload == PAYLOAD and o[0].at == o[1].at
    assert link.counts["duplicate"] == len(twice)


def test_reorder_fraction_and_times():
    """gap 1: every message is eligible; a reordered one is delivered at once, the others after the
    delay, so it overtakes the messages in flight."""
    n, p, c, dt = 20_000, 0.25, 0.05, 0.01
    _, outs = _run(LinkProfile(delay=Delay(constant=c), reorder=Reorder(p=p)), n, dt=dt)
    flat = [o[0] for o in outs]
    reordered = [k for k, d in enumerate(flat) if d.reordered]
    assert _binomial_ok(len(reordered), n, p), len(reordered)
    for k, d in enumerate(flat):
        assert d.at == (k * dt if d.reordered else k * dt + c)
        assert d.event == ("deliver+reorder" if d.reordered else "deliver")
    arrival = np.argsort([d.at for d in flat], kind="stable")
    assert (np.diff(arrival) < 0).mean() > 0.1  # messages really arrive out of order


def test_reorder_gap():
    n = 3000
    _, outs = _run(LinkProfile(delay=Delay(constant=0.05), reorder=Reorder(p=1.0, gap=3)), n)
    assert [k for k, o in enumerate(outs) if o[0].reordered] == list(range(2, n, 3))
    # p < 1: renewal cycles of g-1 ineligible messages then Geometric(p) eligible ones, one reorder
    # per cycle: fraction 1/mu with mu = g-1+1/p; count variance n sigma^2/mu^3, sigma^2 = (1-p)/p^2
    n, p, g = 20_000, 0.5, 3
    _, outs = _run(LinkProfile(delay=Delay(constant=0.05), reorder=Reorder(p=p, gap=g)), n)
    idx = np.array([k for k, o in enumerate(outs) if o[0].reordered])
    mu, var = g - 1 + 1 / p, (1 - p) / p**2
    assert _within(len(idx), n / mu, math.sqrt(n * var / mu**3)), len(idx)
    assert np.diff(idx).min() >= g


@pytest.mark.parametrize("nbytes", [1, 3])
def test_corruption_flips_distinct_bytes(nbytes):
    _, outs = _run(LinkProfile(corrupt=Corrupt(p=1.0, bytes=nbytes)), 2000)
    for o in outs:
        (d,) = o
        assert d.corrupted and d.event == "deliver+corrupt" and len(d.payload) == len(PAYLOAD)
        differ = sum(a != b for a, b in zip(d.payload, PAYLOAD, strict=True))
        assert differ == nbytes


def test_corruption_ratio_and_short_payloads():
    n, p = 20_000, 0.1
    link, outs = _run(LinkProfile(corrupt=Corrupt(p=p)), n)
    bad = [o[0] for o in outs if o[0].corrupted]
    assert _binomial_ok(len(bad), n, p) and link.counts["corrupt"] == len(bad)
    assert all(d.payload != PAYLOAD for d in bad)
    assert all(o[0].payload == PAYLOAD for o in outs if not o[0].corrupted)
    _, outs = _run(LinkProfile(corrupt=Corrupt(p=1.0, bytes=5)), 100, payload=b"ab")
    assert all(o[0].payload != b"ab" and len(o[0].payload) == 2 for o in outs)
    _, outs = _run(LinkProfile(corrupt=Corrupt(p=1.0)), 10, payload=b"")
    assert all(o == [Delivery(k * 0.01, b"", "deliver")] for k, o in enumerate(outs))


# --------------------------------------------------------------------------- rate
def test_rate_limit_throughput_and_queueing_delay():
    """100-byte messages at 10 kB/s take 10 ms each. Offered every 5 ms (twice the rate), message n
    leaves at 10 ms (n+1) and waits 5 ms n in the queue; offered every 20 ms, none waits."""
    rate, size, service = 10_000.0, 100, 0.01
    profile = LinkProfile(rate=Rate(bytes_per_s=rate))
    n = 400
    _, outs = _run(profile, n, dt=0.005, payload=bytes(size))
    at = np.array([o[0].at for o in outs])
    k = np.arange(n)
    np.testing.assert_allclose(at, service * (k + 1), rtol=0, atol=1e-9)
    np.testing.assert_allclose(at - 0.005 * k - service, 0.005 * k, rtol=0, atol=1e-9)
    throughput = (n - 1) * size / (at[-1] - at[0])
    assert throughput == pytest.approx(rate, rel=1e-9)

    _, outs = _run(profile, n, dt=0.02, payload=bytes(size))
    np.testing.assert_allclose([o[0].at - 0.02 * k for k, o in enumerate(outs)], service, rtol=0, atol=1e-12)

    # overhead counts on the wire; the propagation delay comes after the transmitter
    prof = LinkProfile(rate=Rate(bytes_per_s=rate, overhead=28), delay=Delay(constant=0.05))
    _, outs = _run(prof, 10, dt=1.0, payload=bytes(size))
    np.testing.assert_allclose([o[0].at - k for k, o in enumerate(outs)], 0.05 + 128 / rate, rtol=0, atol=1e-12)


def test_rate_limit_queue_tail_drop():
    """Limit 5 at twice the rate: about half the messages find the queue full; the others wait at
    most 5 service times, and the link still carries its rate."""
    rate, size, service, n = 10_000.0, 100, 0.01, 2000
    link, outs = _run(LinkProfile(rate=Rate(bytes_per_s=rate, limit=5)), n, dt=0.005, payload=bytes(size))
    kept = [(k * 0.005, o[0].at) for k, o in enumerate(outs) if o]
    assert link.counts["queue"] == n - len(kept) and abs(len(kept) - n / 2) <= 5
    assert max(at - t for t, at in kept) <= 5 * service + 1e-9
    assert (len(kept) - 1) * size / (kept[-1][1] - kept[0][1]) == pytest.approx(rate, rel=1e-3)
    assert link.last_drop_reason in ("queue", None)


# --------------------------------------------------------------------------- outages
def test_outages_drop_exactly_the_window():
    dt = 1 / 1024
    windows = ((2.0, 3.0), (5.0, 5.5))
    n = 8 * 1024
    link, outs = _run(LinkProfile(outages=windows), n, dt=dt)
    for k, o in enumerate(outs):
        t = k * dt
        inside = any(a <= t < b for a, b in windows)
        assert (o == []) == inside, t
        if inside:
            assert link.counts["outage"] > 0
    assert link.counts["outage"] == (1024 + 512)
    # with a delay, nothing sent in the window arrives and nothing arrives in it (in-flight copies are lost)
    d = 0.125
    _, outs = _run(LinkProfile(outages=windows, delay=Delay(constant=d)), n, dt=dt)
    for k, o in enumerate(outs):
        t = k * dt
        dropped = any(a <= t < b or a <= t + d < b for a, b in windows)
        assert (o == []) == dropped, t
        assert all(not any(a <= x.at < b for a, b in windows) for x in o)
    link, outs = _run(LinkProfile(outages=((1.0, math.inf),)), 200, dt=0.01)
    assert [bool(o) for o in outs] == [k < 100 for k in range(200)]
    assert link.last_drop_reason == "outage"


# --------------------------------------------------------------------------- determinism, state, log
EVERYTHING = LinkProfile(
    delay=Delay(constant=0.01, jitter=0.004, distribution="pareto", correlation=0.4),
    loss=GilbertElliott(p=0.05, r=0.3, bad_loss=0.8, good_loss=0.02), duplicate=0.05,
    reorder=Reorder(p=0.1, gap=2), corrupt=Corrupt(p=0.05, bytes=2),
    rate=Rate(bytes_per_s=20_000.0, overhead=20, limit=4), outages=((3.0, 3.5),))


def _trace(seed: int, src: int = 1, dst: int = 2, switch: bool = False) -> tuple[list, list[Decision]]:
    gen = np.random.default_rng(99)  # the offers: random times and sizes, the same for every trace
    times = np.cumsum(gen.exponential(0.008, 1500)).tolist()
    sizes = gen.integers(0, 300, 1500).tolist()
    link = Link(EVERYTHING, link_rng(seed, src, dst), log=True)
    out = []
    for k, (t, s) in enumerate(zip(times, sizes, strict=True)):
        if switch and k == 700:
            link.set_profile(PRESETS["congested"])
        out.append(link.offer(t, bytes(s)))
    return out, link.take_decisions()


def test_determinism_per_seed():
    a, log_a = _trace(5)
    b, log_b = _trace(5)
    assert a == b and log_a == log_b
    assert _trace(5, switch=True) == _trace(5, switch=True)
    assert _trace(6)[1] != log_a
    assert _trace(5, src=2, dst=1)[1] != log_a


def test_decision_log_records_every_copy():
    outs, log = _trace(5)
    delivered = [d for o in outs for d in o]
    assert [(x.event, x.at) for x in log if x.at is not None] == [(d.event, d.at) for d in delivered]
    assert {x.event.split(":")[1] for x in log if x.at is None} <= set(DROP_REASONS)
    assert {x.seq for x in log} == set(range(len(outs)))
    assert all(x.at is None or x.at >= x.now for x in log)
    # it encodes as is, for the caller to write out
    assert msgspec.json.decode(msgspec.json.encode(log), type=list[Decision]) == log


def test_counts_add_up():
    link = Link(EVERYTHING, link_rng(1, 1, 2))
    copies = sum(len(link.offer(k * 0.01, PAYLOAD)) for k in range(3000))
    c = link.counts
    assert c["offered"] == 3000 and c["delivered"] == copies
    assert c["offered"] + c["duplicate"] + sum(c[r] for r in DROP_REASONS) >= c["delivered"]
    assert all(c[r] > 0 for r in ("loss", "outage", "duplicate", "reorder", "corrupt"))


def test_set_profile_keeps_state_sensibly():
    # Gilbert-Elliott -> Gilbert-Elliott keeps the state; -> Bernoulli starts good
    link = Link(LinkProfile(loss=GilbertElliott(p=1.0, r=1e-9)), link_rng(1, 1, 2))
    link.offer(0.0, PAYLOAD)  # delivered in the good state, then moves to bad for sure
    link.set_profile(LinkProfile(loss=GilbertElliott(p=0.0, r=1e-9)))
    assert all(link.offer(0.01 * k, PAYLOAD) == [] for k in range(1, 100))
    link.set_profile(LinkProfile(loss=Bernoulli(p=0.0)))
    assert link.offer(1.0, PAYLOAD) == [Delivery(1.0, PAYLOAD, "deliver")]
    # the transmitter's backlog finishes at the old rate; new copies queue behind it
    link = Link(LinkProfile(rate=Rate(bytes_per_s=1000.0)), link_rng(1, 1, 2))
    assert [link.offer(0.0, PAYLOAD)[0].at for _ in range(10)] == pytest.approx([0.1 * (k + 1) for k in range(10)])
    link.set_profile(LinkProfile(rate=Rate(bytes_per_s=10_000.0)))
    assert link.offer(0.0, PAYLOAD)[0].at == pytest.approx(1.01)
    link.set_profile(IDENTITY)
    assert link.offer(0.0, PAYLOAD)[0].at == 0.0


def test_now_must_be_finite_and_not_decrease():
    link = Link(EVERYTHING, link_rng(1, 1, 2))
    link.offer(1.0, PAYLOAD)
    link.offer(1.0, PAYLOAD)
    for bad in (0.5, math.nan, math.inf):
        with pytest.raises(ValueError, match="now is"):
            link.offer(bad, PAYLOAD)


def test_link_rng():
    a, b = link_rng(3, 1, 2), link_rng(3, 1, 2)
    assert a.random() == b.random()
    draws = {link_rng(3, s, d).random() for s, d in [(1, 2), (2, 1), (1, 3)]}
    draws |= {link_rng(4, 1, 2).random(), np.random.default_rng([3, 1]).random(),
              np.random.default_rng([3, 1, 2]).random()}
    assert len(draws) == 6
    with pytest.raises(ValueError, match="src is -1"):
        link_rng(0, -1, 2)


def test_delivery_queue_orders_by_time_then_push_order():
    q = DeliveryQueue()
    q.push([Delivery(0.3, b"a", "deliver"), Delivery(0.1, b"b", "deliver")])
    q.push([Delivery(0.3, b"c", "duplicate"), Delivery(0.2, b"d", "deliver")])
    assert len(q) == 4 and q.next_at == 0.1
    assert [d.payload for d in q.pop_due(0.05)] == []
    assert [d.payload for d in q.pop_due(0.2)] == [b"b", b"d"]
    assert [d.payload for d in q.pop_due(1.0)] == [b"a", b"c"]
    assert q.next_at is None and len(q) == 0


# --------------------------------------------------------------------------- validation and presets
BAD = [
    (dict(delay=Delay(constant=-0.01)), "delay.constant", ">= 0"),
    (dict(delay=Delay(jitter=-1.0)), "delay.jitter", ">= 0"),
    (dict(delay=Delay(jitter=0.01, correlation=1.0)), "delay.correlation", "[0, 1)"),
    (dict(delay=Delay(correlation=0.5)), "delay.correlation", "set delay.jitter > 0"),
    (dict(delay=Delay(constant=math.nan)), "delay.constant", "finite"),
    (dict(loss=Bernoulli(p=1.5)), "loss.p", "[0, 1]"),
    (dict(loss=Bernoulli(p=5.0)), "loss.p", "not a percentage"),
    (dict(loss=GilbertElliott(p=0.1, r=-0.1)), "loss.r", "[0, 1]"),
    (dict(loss=GilbertElliott(p=0.1, r=0.0)), "loss.r", "absorbing"),
    (dict(loss=GilbertElliott(p=1.0)), "loss.r", "defaults to 1 - p"),
    (dict(loss=GilbertElliott(p=0.1, r=0.5, bad_loss=2.0)), "loss.bad_loss", "[0, 1]"),
    (dict(loss=GilbertElliott(p=0.1, r=0.5, good_loss=-0.5)), "loss.good_loss", "[0, 1]"),
    (dict(duplicate=1.01), "duplicate", "[0, 1]"),
    (dict(reorder=Reorder(p=0.1, gap=0), delay=Delay(constant=0.01)), "reorder.gap", ">= 1"),
    (dict(reorder=Reorder(p=0.1)), "reorder.p", "delay.constant > 0"),
    (dict(corrupt=Corrupt(p=0.1, bytes=0)), "corrupt.bytes", ">= 1"),
    (dict(corrupt=Corrupt(p=-0.1)), "corrupt.p", "[0, 1]"),
    (dict(rate=Rate(bytes_per_s=-1.0)), "rate.bytes_per_s", ">= 0"),
    (dict(rate=Rate(bytes_per_s=1e4, overhead=-2)), "rate.overhead", ">= 0"),
    (dict(rate=Rate(bytes_per_s=1e4, limit=-1)), "rate.limit", "0 for unbounded"),
    (dict(rate=Rate(limit=10)), "rate.limit", "rate.bytes_per_s > 0"),
    (dict(outages=((2.0, 1.0),)), "outages[0]", "start < end"),
    (dict(outages=((0.0, 1.0), (-1.0, 1.0))), "outages[1]", ">= 0"),
    (dict(outages=((math.inf, math.inf),)), "outages[0]", "finite start"),
]


@pytest.mark.parametrize(("kwargs", "field", "text"), BAD, ids=[f"{f}:{t}" for _, f, t in BAD])
def test_validation_names_the_field_and_the_fix(kwargs, field, text):
    problems = validate(LinkProfile(**kwargs))
    assert [f for f, _ in problems] == [field], problems
    msg = problems[0][1]
    assert text in msg and "; " in msg, msg
    assert validate(LinkProfile(**kwargs), "netem.default")[0][0] == f"netem.default.{field}"
    with pytest.raises(ProfileError) as err:
        Link(LinkProfile(**kwargs), link_rng(0, 1, 2))
    assert err.value.problems == problems


def test_convert_decodes_strictly():
    raw = {"delay": {"constant": 0.01, "jitter": 0.002, "distribution": "normal"},
           "loss": {"kind": "gilbert_elliott", "p": 0.01, "r": 0.3}, "outages": [[1.0, 2.0]]}
    prof = convert(raw)
    assert prof.loss == GilbertElliott(p=0.01, r=0.3) and prof.outages == ((1.0, 2.0),)
    cases = [
        ({"delay": {"constnt": 0.01}}, "delay.constnt", "rename it to `constant`"),
        ({"loss": {"kind": "ge"}}, "loss.kind", "gilbert_elliott"),
        ({"delay": {"distribution": "gauss"}}, "delay.distribution", "normal"),
        ({"duplicate": "1%"}, "duplicate", "expected `float`"),
        ({"loss": {"p": 0.1}}, "loss.kind", "kind = \"bernoulli\""),
        ({"loss": {"kind": "bernoulli", "p": 2.0}}, "loss.p", "[0, 1]"),
        ("wfi", "<profile>", "did you mean `wifi`"),
    ]
    for raw, field, text in cases:
        with pytest.raises(ProfileError) as err:
            convert(raw)
        assert err.value.problems[0][0] == field and text in err.value.problems[0][1], err.value.problems
    assert convert("wifi") is PRESETS["wifi"]


def test_presets_validate_and_are_documented():
    assert set(PRESETS) >= {"ideal", "wifi", "wifi-lossy", "congested", "lossy-burst"}
    assert set(PRESET_NOTES) == set(PRESETS)
    doc = DOC.read_text(encoding="utf-8")
    for name, prof in PRESETS.items():
        assert validate(prof) == [], name
        assert is_identity(prof) == (name == "ideal")
        assert f"`{name}`" in doc, f"docs/netem.md does not describe preset {name}"
        Link(prof, link_rng(0, 1, 2)).offer(0.0, PAYLOAD)
    with pytest.raises(KeyError, match="did you mean `congested`"):
        preset("congestd")


def test_network_schedule():
    net = msgspec.convert({
        "default": "wifi",
        "rules": [
            {"from": 1, "to": 2, "profile": "lossy-burst", "start": 10.0},
            {"profile": "ideal", "start": 20.0},
            {"to": 2, "profile": {"duplicate": 0.1}, "start": 20.0},
        ]}, type=Network)
    dup = LinkProfile(duplicate=0.1)
    assert schedule(net, 1, 2) == [(0.0, PRESETS["wifi"]), (10.0, PRESETS["lossy-burst"]), (20.0, dup)]
    assert schedule(net, 3, 2) == [(0.0, PRESETS["wifi"]), (20.0, dup)]
    assert schedule(net, 1, 3) == [(0.0, PRESETS["wifi"]), (20.0, IDENTITY)]
    assert profile_at(net, 1, 2, 9.99) == PRESETS["wifi"] and profile_at(net, 1, 2, 10.0) == PRESETS["lossy-burst"]
    assert schedule(Network(), 1, 2) == [(0.0, IDENTITY)]
    assert validate_network(net, node_ids={1, 2, 3}) == []
    bad = Network(default="wfi", rules=(LinkRule(profile=LinkProfile(duplicate=2.0), src=9, start=-1.0),))
    fields = [f for f, _ in validate_network(bad, node_ids={1, 2})]
    assert fields == ["netem.default", "netem.rules[0].profile.duplicate", "netem.rules[0].start",
                      "netem.rules[0].from"]
