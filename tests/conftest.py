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
