"""What pytest itself must see for every test: the environment each test process and everything it
starts inherits.

The shared helpers are plain functions imported by name, which a conftest.py is not meant to be:
``tests/support.py`` holds the ``tether`` runners, the one port allocator (:func:`tests.support.free_port`,
for TCP and for the software Crazyflies' UDP), the condition waits and the software Crazyflie process;
``tests/factories.py`` holds the mission builders.
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest


def pytest_configure(config: pytest.Config) -> None:
    """One BLAS thread per process and matplotlib's file backend, for the tests and every process they
    start: the suite may run on every core at once (``pytest -n auto``), and a swarm is a dozen processes, so BLAS
    thread pools would only fight over the same cores; no test has a display. Set only where unset, so
    that a developer's own choice stands. No background compile from the ``tether`` commands the tests
    run (``TETHER_PREWARM=0``, :func:`sim.warm.prewarm`): many of them use caches of their own, and each
    would start one; ``tests/test_warm.py`` turns it on where it is the subject."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    os.environ.setdefault("MPLBACKEND", "Agg")
    os.environ.setdefault("TETHER_PREWARM", "0")


@pytest.hookimpl(trylast=True)  # after ``-m``/``-k`` have deselected: only the tests that will run count
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Deal the files out to the parallel workers (``--dist loadfile``: a file's tests run on one worker,
    so its module fixtures start once) heaviest first, then the rest: a long file dealt out last would
    leave every other worker idle while it runs. Heaviest is most slow tests (real processes, seconds
    each), then most tests. The order within a file stays."""
    weight: dict[str, list[int]] = {}
    for item in items:
        w = weight.setdefault(item.nodeid.partition("::")[0], [0, 0])
        w[0] += item.get_closest_marker("slow") is not None
        w[1] += 1
    items.sort(key=lambda item: [-x for x in weight[item.nodeid.partition("::")[0]]])


REAL_TIME_FILES = frozenset({
    "test_busy_host.py", "test_cfsim.py", "test_cfsim_paths.py", "test_cfsim_trajectory.py", "test_colocate.py",
    "test_crazyflie.py", "test_deploy.py", "test_failsafe_runs.py", "test_faults.py", "test_hold_anchor.py",
    "test_lies.py", "test_observe.py", "test_partition.py", "test_plant_envelope.py", "test_plant_watchdog.py",
    "test_record_crash.py", "test_redteam.py", "test_rehearse.py", "test_rejoin.py",
    "test_relay.py",
    "test_mcap_whole.py", "test_rt_priority.py", "test_runtime.py", "test_runtime_netem.py", "test_secure_run.py",
    "test_shared_plants.py", "test_radio_host.py", "test_radio_link.py", "test_radio_monitor.py", "test_sites.py",
    "test_sitl.py", "test_sitl_example.py", "test_skew.py", "test_lab_plant.py", "test_lab_deadman.py",
    "test_cfsim_lab.py", "test_top_wait.py", "test_live_clients.py", "test_report.py",
})
"""Files whose slow tests fly swarms (or Crazyflies) in real time."""


@pytest.fixture(autouse=True)
def _one_real_time_swarm_at_a_time(request: pytest.FixtureRequest) -> Iterator[None]:
    """A slow test of :data:`REAL_TIME_FILES` holds a lock shared by every test run on the machine (every
    worker of this run, and any other run beside it): two real-time swarms (a dozen processes each, at
    the same real-time priority) on two cores starve each other's ticks, which is not what such a test
    measures. Everything else goes on meanwhile, below the swarm's real-time priority."""
    if request.node.get_closest_marker("slow") is None or request.node.path.name not in REAL_TIME_FILES:
        yield
        return
    lock = Path(tempfile.gettempdir()) / f"tether-real-time-{os.getuid()}.lock"
    with open(lock, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
