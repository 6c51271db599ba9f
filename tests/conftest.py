"""What pytest itself must see for every test: the environment each test process and everything it
starts inherits.

The shared helpers are plain functions imported by name, which a conftest.py is not meant to be:
``tests/support.py`` holds the ``tether`` runners, the one port allocator (:func:`tests.support.free_port`,
for TCP and for the software Crazyflies' UDP), the condition waits and the software Crazyflie process;
``tests/factories.py`` holds the mission builders.
"""

from __future__ import annotations

import os

import pytest


def pytest_configure(config: pytest.Config) -> None:
    """One BLAS thread per process and matplotlib's file backend, for the tests and every process they
    start: the suite runs on every core at once (pytest-xdist), and a swarm is a dozen processes, so BLAS
    thread pools would only fight over the same cores; no test has a display. Set only where unset, so
    that a developer's own choice stands."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    os.environ.setdefault("MPLBACKEND", "Agg")


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
