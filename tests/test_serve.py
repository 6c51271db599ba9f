"""A process's lifetime: ``tether.node.serve`` runs its tasks in one task group and maps how they
end to the exit status (0 finished, 1 failed, 2 bad mission, 143 stopped), leaving no task behind;
a process that never hears the start gives up after ``--start-timeout``.

The in-process cases open a real, isolated Zenoh session (a peer listening on loopback only).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import subprocess
import sys
import threading
import time
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest

from tether import catalog
from tether import transport as tp
from tether import wire
from tether.clock import ClockKind
from tether.node import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, EXIT_STOPPED, LINGER, Node, NodeArgs, serve

REPO = Path(__file__).resolve().parents[1]


def node_args(ns: str, clock: ClockKind = "lockstep", mission: Path | None = None) -> NodeArgs:
    settings = tp.ZenohSettings(mode="peer", listen=(tp.loopback_endpoint(tp.free_tcp_port()),), scouting_delay=0.0)
    return NodeArgs(mission_path=mission or catalog.resolve("section4"), role="leader", node_id=5,
                    clock=clock, zenoh=settings, ns=ns)


def others() -> set[asyncio.Task[object]]:
    return {t for t in asyncio.all_tasks() if t is not asyncio.current_task()}


async def ready_on_start(node: Node, lead: float = 0.0) -> None:
    """``node.ready()``, with the launcher's part played here: the start (tick 0 ``lead`` seconds
    ahead), repeated until it is heard."""
    start = node.publisher(node.keys.start, sender=0)

    async def announce() -> None:
        while True:
            start.send(wire.Start, 0, 0.0, epoch=time.time() + lead)
            await asyncio.sleep(0.05)

    announcer = asyncio.create_task(announce())
    try:
        async with asyncio.timeout(20):
            await node.ready()
    finally:
        announcer.cancel()


async def serve_checked(args: NodeArgs, role: Callable[[Node], Awaitable[None]],
                        on_stop: Callable[[Node], None] | None = None) -> int:
    before = others()
    status = await serve(args, role, on_stop)
    assert others() - before == set(), "serve() left tasks behind"
    return status


@pytest.mark.asyncio
async def test_a_role_that_finishes_exits_0_and_runs_in_the_task_group() -> None:
    seen: list[bool] = []

    async def role(node: Node) -> None:
        seen.append(node.tasks is not None)

    assert await serve_checked(node_args("serve-ok"), role) == EXIT_OK
    assert seen == [True]


@pytest.mark.asyncio
async def test_a_role_that_raises_exits_1_and_on_stop_still_runs() -> None:
    stopped: list[int] = []

    async def role(node: Node) -> None:
        raise RuntimeError("boom")

    status = await serve_checked(node_args("serve-fail"), role, lambda node: stopped.append(1))
    assert status == EXIT_FAILED
    assert stopped == [1]


@pytest.mark.asyncio
async def test_a_stop_cancels_the_role_and_exits_143() -> None:
    cancelled: list[bool] = []

    async def role(node: Node) -> None:
        node.stop.set()  # as SIGTERM's handler does
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            cancelled.append(True)
            raise

    assert await serve_checked(node_args("serve-stop"), role) == EXIT_STOPPED
    assert cancelled == [True]


@pytest.mark.asyncio
async def test_a_role_failing_while_being_stopped_exits_1() -> None:
    async def role(node: Node) -> None:
        node.stop.set()
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            raise RuntimeError("cleanup failed") from None

    assert await serve_checked(node_args("serve-stop-fail"), role) == EXIT_FAILED


@pytest.mark.asyncio
async def test_a_bad_mission_exits_2(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("name = ")

    async def role(node: Node) -> None:
        raise AssertionError("a bad mission runs no role")

    assert await serve_checked(node_args("serve-bad", mission=bad), role) == EXIT_BAD_INPUT


@pytest.mark.asyncio
async def test_the_real_time_input_pump_is_owned_by_the_group_and_ends_with_the_role() -> None:
    pumps: list[asyncio.Task[object]] = []

    async def role(node: Node) -> None:
        await ready_on_start(node, lead=0.05)
        pumps.extend(t for t in asyncio.all_tasks() if t.get_name() == "input pump")
        assert len(pumps) == 1 and not pumps[0].done()

    assert await serve_checked(node_args("serve-pump", clock="realtime"), role) == EXIT_OK
    assert len(pumps) == 1 and pumps[0].cancelled()


@pytest.mark.asyncio
async def test_a_lockstep_member_closes_only_on_the_launchers_word_that_every_sample_is_recorded() -> None:
    """After its last tick a lockstep process keeps its session open until the launcher says the
    recorder holds every sample (``Recorded``), however long that takes: a forged word (another
    sender) and a malformed one are dropped and counted, a word for an earlier tick is not the end,
    and it keeps waiting; the launcher's own word for the last tick ends the wait, exit 0."""
    args = node_args("serve-recorded")
    done: dict[str, float] = {}
    checks: list[asyncio.Task[None]] = []

    async def role(node: Node) -> None:
        word = node.publisher(node.keys.recorded, sender=0)
        forged = node.publisher(node.keys.recorded, sender=3)
        m = node.mission

        async def launcher_at_the_end() -> None:
            forged.send(wire.Recorded, m.steps, m.duration)
            node.session.put(node.keys.recorded, b"\xc1 not msgpack")
            word.send(wire.Recorded, m.steps - 1, m.duration - m.dt)
            drops = node.receiver.drops
            heard = node.sources[node.keys.recorded]
            async with asyncio.timeout(20):
                while drops.get("sender", 0) < 1 or drops.get("malformed", 0) < 1 or heard.received < 1:
                    await asyncio.sleep(0.01)
                # well past the 0.25 s the process used to wait on a timer
                while time.monotonic() < done["role"] + 4 * LINGER:
                    await asyncio.sleep(0.01)
            assert not serving.done(), "closed before the launcher's word"
            done["word"] = time.monotonic()
            word.send(wire.Recorded, m.steps, m.duration)

        await ready_on_start(node)
        done["role"] = time.monotonic()
        checks.append(asyncio.create_task(launcher_at_the_end()))

    serving = asyncio.create_task(serve(args, role))
    async with asyncio.timeout(60):
        status = await serving
    assert "word" in done, "the process closed before the launcher's word"
    await checks[0]  # its own assertions
    assert status == EXIT_OK


@pytest.mark.asyncio
async def test_until_returns_when_woken_from_another_thread_and_raises_stalled_at_its_timeout() -> None:
    """``Node.until``: a condition made true on another thread (as Zenoh's callbacks do) ends the
    wait; one that stays false raises :class:`Stalled` naming what it waited for once the timeout
    has passed, not before; no timer of a wait is left scheduled on the loop."""
    from tether.node import Stalled

    seen: list[object] = []

    async def role(node: Node) -> None:
        loop = asyncio.get_running_loop()
        flag = threading.Event()
        t0 = time.monotonic()  # before the timers start: they fire no earlier than their delay after it
        threading.Timer(0.2, lambda: (flag.set(), node.wakeup.notify())).start()
        await node.until(flag.is_set, 10.0, "the flag")
        seen.append(time.monotonic() - t0)
        t0 = time.monotonic()
        with pytest.raises(Stalled, match="waited 0.3 s for what never comes"):
            await node.until(lambda: False, 0.3, lambda: "what never comes")
        seen.append(time.monotonic() - t0)
        # a wake-up that is not the awaited condition does not end a wait without a timeout
        later = threading.Event()
        t0 = time.monotonic()
        threading.Timer(0.1, node.wakeup.notify).start()
        threading.Timer(0.3, lambda: (later.set(), node.wakeup.notify())).start()
        await node.until(later.is_set, None, "later")
        seen.append(time.monotonic() - t0)
        seen.append([h for h in loop._scheduled if not h.cancelled()])  # type: ignore[attr-defined]

    assert await serve_checked(node_args("serve-until"), role) == EXIT_OK
    woke, stalled, untimed, timers = seen
    # (the loop may run a timer a clock resolution early: 10 ms of slack below the bound)
    assert 0.2 <= woke < 5.0 and 0.29 <= stalled < 5.0 and 0.3 <= untimed < 5.0  # type: ignore[operator]
    assert not any("alarm" in repr(h) for h in timers), timers  # type: ignore[attr-defined]


@pytest.mark.asyncio
async def test_a_lockstep_member_without_the_launchers_word_closes_after_the_stall_timeout(
        caplog: pytest.LogCaptureFixture) -> None:
    """No launcher to say the run is recorded (it is gone; the run has failed by then): the process
    closes after ``--stall-timeout``, says so, and its own work ended well (exit 0)."""
    args = dataclasses.replace(node_args("serve-no-word"), stall_timeout=1.0)
    ended: list[float] = []

    async def role(node: Node) -> None:
        await ready_on_start(node)
        ended.append(time.monotonic())

    with caplog.at_level(logging.WARNING, logger="tether"):
        assert await serve_checked(args, role) == EXIT_OK
    assert time.monotonic() - ended[0] >= 1.0
    assert "waited 1 s for the launcher's word that every sample is recorded: closing anyway" in caplog.text


def test_a_process_that_never_hears_the_start_fails_after_its_start_timeout() -> None:
    """No launcher: the process is ready, no start comes, it gives up with exit 1 naming the wait."""
    endpoint = tp.loopback_endpoint(tp.free_tcp_port())
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "cli", "leader", "--mission", "section4", "--clock", "realtime",
                        "--ns", "start-timeout", "--zenoh-mode", "peer", "--listen", endpoint,
                        "--start-timeout", "1.5"],
                       cwd=REPO, capture_output=True, text=True, timeout=60)
    took = time.monotonic() - t0
    assert r.returncode == 1, r.stderr
    assert "waited 1.5 s for the launcher's start message (--start-timeout)" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
    assert took >= 1.5


def test_the_start_timeout_must_be_a_positive_number_of_seconds() -> None:
    r = subprocess.run([sys.executable, "-m", "cli", "leader", "--mission", "section4", "--start-timeout", "0"],
                       cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "--start-timeout" in r.stderr and "seconds > 0" in r.stderr
