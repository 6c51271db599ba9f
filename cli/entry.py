"""The ``tether`` command's first statements: an operator's order takes its CPU priority before
anything is imported, then :func:`cli.main.main` runs.

``tether land`` and ``tether estop`` are what a human sends when something is wrong, often on a
host that is busy for that very reason: their process runs one ``SCHED_RR`` step below the control
loops (:func:`deploy.operator.take_priority`) from its first statement, so that importing the
command, opening its session and sending the order all preempt whatever else the host is doing.
"""

from __future__ import annotations

import sys

ORDERS = ("land", "estop")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ORDERS:
        from tether import sched

        sched.apply_best(sched.gateway_priority(sched.DEFAULT_PRIORITY))  # said again, and logged, by the order
    from cli.main import main as run

    return run(argv)
