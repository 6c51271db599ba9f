"""The thread-to-loop hand-off: how a Zenoh callback thread passes work to a process's event loop.

Callbacks run on threads Zenoh owns; they only copy into a sink and poke a :class:`Wakeup`:

* :class:`LatestSlot` (state: the newest value supersedes; overwrites counted);
* :class:`BoundedFifo` (commands and events: bounded, drop-oldest, drops counted);
* :class:`InputQueue` (one input key in real time: a bounded FIFO that admits the first samples of
  each tick and drops a flood's excess as it comes, then the oldest).

A callback that does more than hand off (a tap that publishes a relay from Zenoh's thread) runs
inside a :class:`TapGuard`, so that closing never undeclares an object a callback is using.

Nothing here imports Zenoh; the event loop drains the sinks.
"""

from __future__ import annotations

import asyncio
import collections
import threading
from collections.abc import Callable
from typing import Generic, Protocol, TypeVar

T = TypeVar("T")
T_contra = TypeVar("T_contra", contravariant=True)


# =========================================================================== callbacks that publish
class TapGuard:
    """Lets callbacks on Zenoh's threads use shared Zenoh objects while the owner may close them.

    A callback runs its work only between :meth:`enter` (False once closed: skip the work) and
    :meth:`leave`; any number may run at once. :meth:`close` refuses new entries and blocks until
    those running have left (at most ``timeout`` [s]). Zenoh's Python objects are borrowed while a
    call on them runs, and undeclaring one that another thread is putting on raises ``RuntimeError:
    Already borrowed``: close this guard first, then undeclare."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._active = 0
        self._closed = False

    def enter(self) -> bool:
        """Whether the caller may run its work now (then it must :meth:`leave`). Never blocks long."""
        with self._cond:
            if self._closed:
                return False
            self._active += 1
            return True

    def leave(self) -> None:
        with self._cond:
            self._active -= 1
            if self._active == 0:
                self._cond.notify_all()

    def close(self, timeout: float) -> bool:
        """Refuse new entries and wait for those inside to leave; whether they all did within
        ``timeout`` [s]. Blocks."""
        with self._cond:
            self._closed = True
            return self._cond.wait_for(lambda: self._active == 0, timeout)

    @property
    def closed(self) -> bool:
        return self._closed


# =========================================================================== hand-off sinks
class Wakeup:
    """Wakes one asyncio task from any thread, cheaply: many notifications coalesce into one wake-up.

    ``notify()`` may be called from Zenoh's threads; it never blocks beyond a short lock and, at most
    once per wake-up, schedules ``Event.set`` on the loop with ``call_soon_threadsafe``. ``wait()`` runs
    on the loop. A notification that arrives after the loop has closed is ignored. Data written
    before a ``notify()`` is visible to the task once ``wait()`` returns.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop | None = None):
        """Bind to ``loop`` (default: the running loop; then call from inside it)."""
        self._loop = loop if loop is not None else asyncio.get_running_loop()
        self._event = asyncio.Event()
        self._lock = threading.Lock()
        self._pending = False

    def notify(self) -> None:
        """Ask for a wake-up. Thread-safe, returns immediately."""
        with self._lock:
            if self._pending:
                return
            self._pending = True
        try:
            self._loop.call_soon_threadsafe(self._event.set)
        except RuntimeError:  # the loop is closed: nobody is left to wake
            pass

    def notify_here(self) -> None:
        """:meth:`notify` from the loop's own thread (no self-pipe write)."""
        with self._lock:
            self._pending = True
        self._event.set()

    async def wait(self, timeout: float | None = None) -> bool:
        """Sleep until notified (or ``timeout`` [s]); ``True`` if notified. Re-arms before returning."""
        if not self._event.is_set():
            if timeout is None:
                await self._event.wait()
            else:
                try:
                    async with asyncio.timeout(timeout):
                        await self._event.wait()
                except TimeoutError:
                    return False
        self._event.clear()
        with self._lock:
            self._pending = False
        return True


class Sink(Protocol[T_contra]):
    """Where a callback hands a value off. ``put`` is called on Zenoh's threads and must not block."""

    def put(self, item: T_contra, /) -> None: ...


class LatestSlot(Generic[T]):
    """The newest value, written by a callback thread and read by the control loop.

    Overflow policy: **overwrite**. ``put`` replaces whatever is held; a value replaced before anyone
    ``take``-s it is lost and counted in :attr:`overwritten`. Readers always see the newest value.
    ``put`` is thread-safe and never blocks beyond a short lock; it notifies the optional
    :class:`Wakeup`. Invariant: ``written == taken + overwritten + (1 if fresh else 0)``.
    """

    def __init__(self, wakeup: Wakeup | None = None):
        self._lock = threading.Lock()
        self._value: T | None = None
        self._fresh = False
        self._written = 0
        self._taken = 0
        self._overwritten = 0
        self._wakeup = wakeup

    def put(self, item: T, /) -> None:
        """Store ``item`` as the newest value (any thread; returns immediately)."""
        with self._lock:
            if self._fresh:
                self._overwritten += 1
            self._value = item
            self._fresh = True
            self._written += 1
        if self._wakeup is not None:
            self._wakeup.notify()

    def take(self) -> T | None:
        """The newest value if it has not been taken yet, else ``None``. Marks it taken."""
        with self._lock:
            if not self._fresh:
                return None
            self._fresh = False
            self._taken += 1
            return self._value

    def peek(self) -> T | None:
        """The newest value, taken or not (``None`` before the first ``put``). Changes nothing."""
        with self._lock:
            return self._value

    @property
    def fresh(self) -> bool:
        """Whether a value is waiting that has not been taken."""
        return self._fresh

    @property
    def written(self) -> int:
        """Values ever put."""
        return self._written

    @property
    def taken(self) -> int:
        """Values handed out by :meth:`take`."""
        return self._taken

    @property
    def overwritten(self) -> int:
        """Values replaced before being taken (lost to the overwrite policy)."""
        return self._overwritten


class BoundedFifo(Generic[T]):
    """A bounded first-in-first-out queue, written by a callback thread and drained by the asyncio side.

    Overflow policy: **drop the oldest**. When ``capacity`` items are queued, ``put`` discards the
    oldest one to make room and counts it in :attr:`dropped`; ``put`` never blocks (beyond a short
    lock), so a slow reader can never stall Zenoh's threads. Notifies the optional :class:`Wakeup`.
    Invariant: ``written == popped + dropped + len(self)``.
    """

    def __init__(self, capacity: int, wakeup: Wakeup | None = None):
        if not isinstance(capacity, int) or isinstance(capacity, bool) or capacity < 1:
            raise ValueError(f"capacity is {capacity!r}; a BoundedFifo holds at least 1 item")
        self._capacity = capacity
        self._items: collections.deque[T] = collections.deque()
        self._lock = threading.Lock()
        self._written = 0
        self._popped = 0
        self._dropped = 0
        self._wakeup = wakeup

    def put(self, item: T, /) -> None:
        """Append ``item``, dropping the oldest if full (any thread; returns immediately)."""
        with self._lock:
            if len(self._items) >= self._capacity:
                self._items.popleft()
                self._dropped += 1
            self._items.append(item)
            self._written += 1
        if self._wakeup is not None:
            self._wakeup.notify()

    def pop(self) -> T | None:
        """The oldest queued item, or ``None`` if empty."""
        with self._lock:
            if not self._items:
                return None
            self._popped += 1
            return self._items.popleft()

    def drain(self) -> list[T]:
        """Every queued item, oldest first; empties the queue."""
        if not self._items:  # the usual case at a drain; a put racing this is taken at the next one
            return []
        with self._lock:
            out = list(self._items)
            self._items.clear()
            self._popped += len(out)
            return out

    def __len__(self) -> int:
        return len(self._items)

    @property
    def capacity(self) -> int:
        """Most items held at once."""
        return self._capacity

    @property
    def written(self) -> int:
        """Items ever put."""
        return self._written

    @property
    def popped(self) -> int:
        """Items handed out by :meth:`pop` and :meth:`drain`."""
        return self._popped

    @property
    def dropped(self) -> int:
        """Items discarded by the drop-oldest policy."""
        return self._dropped


PER_TICK = 2
"""Samples of one tick an :class:`InputQueue` with a ``tick_of`` admits: the first two. A sender
sends one sample a tick, so a second is already a conflict (:meth:`tether.inputs.Source.offer`
needs the genuine one and one other to see it); more are a flood, dropped as they come."""
TICKS_KEPT = 64
"""Ticks an :class:`InputQueue` remembers the admitted samples of (at least; four queues' worth
for a longer queue): a copy of a tick older than that is admitted again, and then judged by the
reader as a late copy."""


class InputQueue(BoundedFifo[T]):
    """One input key's queue (real time): a :class:`BoundedFifo` (bounded, drop-oldest, counted)
    that its reader may **mute** once it has used its decoding budget for the current period. A
    muted queue still keeps the newest ``capacity`` items (a flood costs one append and, when full,
    one drop per message on Zenoh's thread) but wakes nobody, so that a flood cannot keep the event
    loop busy; the reader unmutes it at the next period.

    Overflow policy with ``tick_of`` (the tick an item says it is of, None if it says none): the
    first :data:`PER_TICK` items of each tick are admitted, and any later item of a tick that has
    had as many is **dropped as it comes** and counted in :attr:`excess`; only then does the
    drop-oldest policy apply. A flood of copies of one key's samples (a forger's) therefore cannot
    evict the genuine sample of a tick before it is decoded: the reader sees the first two samples
    of every tick, which is what the conflict rule needs. ``tick_of`` runs on Zenoh's thread: it
    must be cheap and never raise. Invariant: ``written == popped + dropped + excess + len(self)``."""

    def __init__(self, capacity: int, wakeup: Wakeup | None = None,
                 tick_of: Callable[[T], int | None] | None = None):
        super().__init__(capacity, wakeup)
        self.muted = False
        self._tick_of = tick_of
        self._admitted: dict[int, int] = {}
        """Tick -> items of it admitted, for the newest :attr:`_ticks_kept` ticks seen (insertion order)."""
        self._ticks_kept = max(TICKS_KEPT, 4 * capacity)
        self._excess = 0

    def put(self, item: T, /) -> None:
        k = self._tick_of(item) if self._tick_of is not None else None
        with self._lock:
            self._written += 1
            if k is not None:
                admitted = self._admitted
                n = admitted.get(k, 0)
                if n >= PER_TICK:
                    self._excess += 1
                    return
                admitted[k] = n + 1
                if n == 0 and len(admitted) > self._ticks_kept:
                    del admitted[next(iter(admitted))]
            if len(self._items) >= self._capacity:
                self._items.popleft()
                self._dropped += 1
            self._items.append(item)
        if self._wakeup is not None and not self.muted:
            self._wakeup.notify()

    @property
    def excess(self) -> int:
        """Items dropped as they came: a tick's beyond the first :data:`PER_TICK` (``tick_of``)."""
        return self._excess

    def quieten(self) -> None:
        """Wake nobody from now on (the reader drains this queue on its own schedule)."""
        self._wakeup = None

    def take(self, n: int) -> list[T]:
        """At most ``n`` queued items, oldest first."""
        with self._lock:
            out = [self._items.popleft() for _ in range(min(n, len(self._items)))]
            self._popped += len(out)
            return out
