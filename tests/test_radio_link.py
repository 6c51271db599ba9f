"""The software Crazyflie's Crazyradio-like link (``python -m plant.cfsim --radio``): the pure model
(:class:`plant.cfsim.realism.Radio`: bounded retries, in-order arrival, airtime shared per dongle) and
real cflib connecting and logging through it."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from plant.cfsim.realism import DOWN, UP, Radio, RadioConfig
from tests.support import free_port, software_crazyflies, wait_until


# =========================================================================== the pure model
def test_retries_turn_one_percent_attempt_loss_into_almost_none() -> None:
    radio = Radio(RadioConfig(rate=1e6, loss=0.01, retries=3, seed=3))
    for k in range(200_000):
        radio.transmit(k * 1e-4, UP)
    n = radio.counts
    assert n.lost[UP] == 0  # 0.01 ** 4 per packet: 2e-3 expected in 2e5
    assert n.sent[UP] == 200_000
    assert n.attempts[UP] == pytest.approx(200_000 * (1 + 0.01), rel=0.01)  # one retry per hundred


def test_a_packet_is_lost_after_its_retries_and_counted() -> None:
    radio = Radio(RadioConfig(rate=1e6, loss=0.5, retries=2, seed=1))
    got = [radio.transmit(k * 1e-3, DOWN) for k in range(20_000)]
    n = radio.counts
    assert n.lost[DOWN] == sum(g is None for g in got)
    assert n.lost[DOWN] / 20_000 == pytest.approx(0.5 ** 3, abs=0.01)
    assert n.attempts[DOWN] / 20_000 == pytest.approx(1 + 0.5 + 0.25, abs=0.02)
    assert n.lost[UP] == n.sent[UP] == 0


def test_jitter_delays_and_never_reorders_a_stream() -> None:
    radio = Radio(RadioConfig(rate=1000.0, latency=0.005, jitter=0.030, seed=2))
    last, arrivals = -np.inf, []
    for k in range(2000):
        now = k * 0.002
        at = radio.transmit(now, DOWN, last)
        assert at is not None and at >= now + 0.001 + 0.005  # one slot of airtime, then the latency
        arrivals.append(at)
        last = at
    assert np.all(np.diff(arrivals) >= 0.0)
    assert max(np.array(arrivals) - 0.002 * np.arange(2000)) > 0.030  # the jitter is there


def test_airtime_is_shared_by_the_dongles_vehicles_and_bounded() -> None:
    rate = 1000.0
    radio = Radio(RadioConfig(rate=rate, queue=0.0505))
    # four vehicles, each sending 100 packets at once on the same dongle: one slot each, in turn
    ats = [radio.transmit(0.0, UP) for _ in range(400)]
    sent = [a for a in ats if a is not None]
    assert len(sent) == 51  # waits of 0..50 slots; what waits longer than the queue allows is dropped
    assert radio.counts.overflow[UP] == 400 - len(sent)
    np.testing.assert_allclose(np.diff(sent), 1.0 / rate, rtol=0, atol=1e-12)
    assert radio.transmit(0.0, DOWN) == pytest.approx(1.0 / rate)  # the other way has its own airtime


@pytest.mark.parametrize("field,value", [("rate", 0.0), ("loss", 1.5), ("retries", -1), ("retries", 16),
                                         ("jitter", float("nan")), ("degrade", ((-1.0, 0.5),)),
                                         ("degrade", ((2.0, 0.5), (1.0, 0.1))), ("degrade", ((1.0, 2.0),))])
def test_absurd_radio_settings_are_refused_naming_the_field(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field.split("_")[0]):
        RadioConfig(**{field: value})  # type: ignore[arg-type]


def test_degradation_starts_at_its_time() -> None:
    radio = Radio(RadioConfig(rate=1e6, loss=0.0, retries=0, degrade=((1.0, 1.0), (2.0, 0.0))))
    assert radio.transmit(0.999, UP) is not None
    assert radio.transmit(1.0, UP) is None
    assert radio.transmit(2.0, UP) is not None


# =========================================================================== real cflib through it
cflib_crtp = pytest.importorskip("cflib.crtp")
from cflib.crazyflie import Crazyflie  # noqa: E402
from cflib.crazyflie.log import LogConfig  # noqa: E402

CONNECT = 30.0
"""Upper bound [s] on a cold connection (TOC and every parameter downloaded) on a loaded machine."""


@contextlib.contextmanager
def _links(uris: list[str]) -> Iterator[tuple[list[Crazyflie], list[threading.Event], list[list[str]]]]:
    cfs, ready, failed = [], [], []
    try:
        for uri in uris:
            cf = Crazyflie(rw_cache=None)  # cold: the whole TOC and every parameter over the lossy link
            ev, why = threading.Event(), []
            cf.fully_connected.add_callback(lambda _u, ev=ev: ev.set())
            cf.connection_failed.add_callback(lambda _u, msg, ev=ev, why=why: (why.append(msg), ev.set()))
            cfs.append(cf)
            ready.append(ev)
            failed.append(why)
            cf.open_link(uri)
        yield cfs, ready, failed
    finally:
        for cf in cfs:
            cf.close_link()


@pytest.mark.slow
def test_four_cold_connects_of_four_succeed_at_one_percent_loss() -> None:
    base = free_port(4, udp=True)
    with software_crazyflies(["--count", "4", "--base-port", str(base), "--radio", "--loss", "0.01", "--seed", "5",
                              "--log-level", "INFO"]) as sim:
        cflib_crtp.init_drivers()
        with _links([sim.uris[i] for i in range(4)]) as (_cfs, ready, failed):
            wait_until(lambda: all(ev.is_set() for ev in ready), CONNECT, "four cold connections", sim.proc)
            assert failed == [[], [], [], []]
        sim.proc.terminate()
        assert sim.proc.wait(timeout=10) == 0
    wait_until(lambda: any(" radio 0: up " in line for line in sim.stderr), 5.0, "the radio's counts")
    counts = next(line for line in sim.stderr if " radio 0: up " in line)
    retried = [int(w) for w in counts.replace(",", "").split() if w.isdigit()]
    # up: sent, lost, dropped, attempts; down: the same. Losses were retried, not passed on.
    assert retried[1] == retried[2] == 0 and retried[3] > retried[0], counts


@pytest.mark.slow
def test_jitter_never_reorders_a_log_stream() -> None:
    base = free_port(1, udp=True)
    with software_crazyflies(["--count", "1", "--base-port", str(base), "--radio", "--jitter", "30",
                              "--log-level", "WARNING"]) as sim:
        cflib_crtp.init_drivers()
        stamps: list[int] = []
        with _links([sim.uris[0]]) as (cfs, ready, failed):
            wait_until(lambda: ready[0].is_set(), CONNECT, "the connection", sim.proc)
            assert not failed[0]
            conf = LogConfig("order", 10)
            conf.add_variable("stateEstimate.z", "float")
            conf.data_received_cb.add_callback(lambda stamp, _d, _c: stamps.append(stamp))
            cfs[0].log.add_config(conf)
            conf.start()
            wait_until(lambda: len(stamps) >= 200, 20.0, "200 log packets", sim.proc)
    gaps = np.diff(stamps)
    assert np.all(gaps > 0), f"reordered: {stamps}"
    assert np.all(gaps == 10)  # and none lost: a loss-free radio delivers every one
