"""The event loop every tether process runs on: uvloop where it is installed, else asyncio's own.

Why uvloop: an agent's tick is mostly wake-ups, hand-offs from Zenoh's threads and short callbacks,
and asyncio's loop is Python at every step of them. Measured on a 2-vCPU machine (``bench/ab.py
--mixed``: half the vehicles of one swarm on each loop, see ``docs/benchmarks.md``):
section4 in lockstep, an agent's main thread 0.86 of its CPU per tick with uvloop, the whole
process 0.90, 6 of 6 runs; its plant 0.89.

``TETHER_LOOP`` chooses, for a process and every process it starts (they inherit it):

* unset: uvloop if it can be imported, else asyncio (``pip install tether`` brings uvloop on
  Linux and macOS; there is none for Windows);
* ``uvloop``: uvloop or an error (exit 2) if it is not installed;
* ``asyncio``: the standard library's loop (to compare, or for asyncio's debug mode).

Timers: uvloop's run on libuv's millisecond clock, rounded, and can fire up to about a
millisecond before their instant (asyncio's never fire early: they are rounded up, and fire
0.2-2 ms late). A wait that must not end before an instant (:meth:`tether.clock.RealtimeClock.wait_for`)
checks the clock and sleeps again, at least :data:`TIMER_GRAIN`, so that a shorter rest is not
rounded to zero and spun on.
"""

from __future__ import annotations

import os
from collections.abc import Coroutine, Mapping
from typing import Any, TypeVar

T = TypeVar("T")

ENV = "TETHER_LOOP"
CHOICES = ("uvloop", "asyncio")

TIMER_GRAIN = 0.001
"""The shortest sleep [s] worth asking an event loop for (uvloop rounds timers to milliseconds: a
shorter one fires at once)."""


class LoopError(ValueError):
    """``TETHER_LOOP`` names no loop this process can run: the message names the variable and the fix."""


def choose(environ: Mapping[str, str] = os.environ) -> str:
    """The loop this process runs on (``uvloop`` or ``asyncio``), from ``TETHER_LOOP``;
    :class:`LoopError` if it asks for one that is unknown or not installed."""
    want = environ.get(ENV, "").strip()
    if want and want not in CHOICES:
        raise LoopError(f"{ENV}={want!r} is not a loop; set it to uvloop or asyncio, or unset it "
                        "(uvloop where it is installed)")
    if want == "asyncio":
        return "asyncio"
    try:
        import uvloop  # noqa: F401
    except ImportError:
        if want == "uvloop":
            raise LoopError(f"{ENV}=uvloop, but uvloop is not installed: pip install uvloop, "
                            f"or set {ENV}=asyncio") from None
        return "asyncio"
    return "uvloop"


def run(main: Coroutine[Any, Any, T], kind: str | None = None) -> T:
    """``asyncio.run(main)`` on the loop :func:`choose` picks (or ``kind``)."""
    import asyncio  # here: a process's command line is parsed before it needs the loop (tests/test_imports.py)

    kind = kind or choose()
    if kind == "uvloop":
        import uvloop

        with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
            return runner.run(main)
    return asyncio.run(main)


def running() -> str:
    """The kind of the running loop (``uvloop`` or ``asyncio``), for the log and the tests."""
    import asyncio

    return "uvloop" if type(asyncio.get_running_loop()).__module__.startswith("uvloop") else "asyncio"
