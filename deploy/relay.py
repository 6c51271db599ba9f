"""A TCP relay between one process and the launcher's router, which can cut that process off.

``tether run --fault partition:agent/3@8+2`` starts agent 3 connected to a relay on a free
loopback port instead of to the router directly; the relay forwards every byte both ways. While
the relay is *cut*, it forwards nothing (a black hole: no reset, no close, nothing acknowledged
end to end), and a connection opened meanwhile is accepted but not forwarded until the cut ends.

What that emulates: the one link between that process and the rest of the swarm going silent,
as a radio out of range does. Zenoh on both sides stops hearing the other's keep-alives and drops
the link after its lease (``--lease``): the others see the process's liveliness token go, the
process sees theirs go, and the client reconnects once the relay forwards again (its lost
declarations are restored by Zenoh). A cut shorter than the lease is a stall: the bytes held in
the relay and the kernel's buffers are delivered late, in order, as TCP would after a healed link.

What it does not emulate: packet loss or reordering inside the link (TCP hides those), a
partition between two groups of processes (only the victim's link to the router is cut), or
links the process has to anyone else (with ``--network mesh`` peers link directly: the launcher
refuses a partition there). No root, no network namespace: the relay runs in the launcher.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

log = logging.getLogger("tether")

CHUNK = 1 << 16


class Relay:
    """Forward connections on ``127.0.0.1:<port>`` to ``upstream`` (``host``, ``port``).

    Create with :meth:`start` (an async factory); :meth:`cut` and :meth:`restore` gate the
    forwarding; :meth:`close` ends every connection. Runs on the caller's event loop."""

    def __init__(self, upstream: tuple[str, int]):
        self.upstream = upstream
        self._open = asyncio.Event()
        self._open.set()
        self._server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._writers: set[asyncio.StreamWriter] = set()
        self.port = 0
        self.connections = 0
        """Connections accepted so far."""

    @classmethod
    async def start(cls, upstream: tuple[str, int]) -> "Relay":
        relay = cls(upstream)
        relay._server = await asyncio.start_server(relay._accept, "127.0.0.1", 0)
        relay.port = relay._server.sockets[0].getsockname()[1]
        return relay

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    @property
    def is_cut(self) -> bool:
        return not self._open.is_set()

    def cut(self) -> None:
        """Stop forwarding (returns at once)."""
        self._open.clear()

    def restore(self) -> None:
        """Forward again, held bytes first."""
        self._open.set()

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        self._writers.add(writer)
        try:
            await self._open.wait()  # a connection opened during a cut waits for its end
            up_reader, up_writer = await asyncio.open_connection(*self.upstream)
        except OSError as exc:
            log.warning("relay to %s:%d: %s", *self.upstream, exc)
            writer.close()
            self._writers.discard(writer)
            return
        self._writers.add(up_writer)
        pumps = [asyncio.create_task(self._pump(reader, up_writer)), asyncio.create_task(self._pump(up_reader, writer))]
        self._tasks.update(pumps)
        try:
            await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in pumps:
                t.cancel()
                self._tasks.discard(t)
            for w in (writer, up_writer):
                w.close()
                self._writers.discard(w)

    async def _pump(self, src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
        with contextlib.suppress(OSError, ConnectionError):
            while data := await src.read(CHUNK):
                await self._open.wait()
                dst.write(data)
                await dst.drain()

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
        self._open.set()
        for t in list(self._tasks):
            t.cancel()
        for w in list(self._writers):
            w.close()
        self._tasks.clear()
        self._writers.clear()
