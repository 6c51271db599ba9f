"""Both names of the Foxglove WebSocket protocol on the live view's port.

The Foxglove SDK's server (foxglove-sdk 0.30) accepts a WebSocket only under the subprotocol name
``foxglove.sdk.v1``; clients written before it (Lichtblick before Dec 2025, ``foxglove.websocket.v1``
libraries) offer only ``foxglove.websocket.v1`` and get HTTP 400. The frames of both are the same
protocol. :class:`Shim` listens on the live view's public port and splices every connection to
the SDK's server on a loopback port; for a client that offers ``foxglove.websocket.v1`` and not
``foxglove.sdk.v1`` it renames the subprotocol in the opening handshake (the request's
``Sec-WebSocket-Protocol`` header, and the response's back), and touches nothing after it. The
accept key does not depend on the subprotocol, so the handshake stays valid.

It runs on a thread of its own with its own event loop (the simulator's live view has none);
the public socket is bound in the constructor, so a port in use fails there.
"""

from __future__ import annotations

import asyncio
import re
import socket
import threading

SDK = "foxglove.sdk.v1"
LEGACY = "foxglove.websocket.v1"
HEAD_LIMIT = 65536
"""Largest opening handshake read [bytes]; a longer one is refused (connection closed)."""
_PROTOCOL = re.compile(rb"(?im)^sec-websocket-protocol:[ \t]*([^\r\n]*)\r\n")


def offered(head: bytes) -> list[str]:
    """The subprotocols an HTTP upgrade request offers (every ``Sec-WebSocket-Protocol`` header)."""
    return [p.strip() for m in _PROTOCOL.finditer(head) for p in m.group(1).decode("latin-1").split(",") if p.strip()]


def rename_request(head: bytes) -> tuple[bytes, bool]:
    """The request with ``foxglove.websocket.v1`` asked as ``foxglove.sdk.v1`` when it offers the
    first and not the second, and whether it was renamed. Pure."""
    names = offered(head)
    if SDK in names or LEGACY not in names:
        return head, False
    return _PROTOCOL.sub(f"Sec-WebSocket-Protocol: {SDK}\r\n".encode(), head, count=1), True


def rename_response(head: bytes) -> bytes:
    """The server's handshake response with its chosen ``foxglove.sdk.v1`` named
    ``foxglove.websocket.v1``, as the client asked. Pure."""
    return _PROTOCOL.sub(f"Sec-WebSocket-Protocol: {LEGACY}\r\n".encode(), head, count=1)


class Shim:
    """Listens on ``host:port`` (0: any free port, :attr:`port` says which) and splices each
    connection to ``127.0.0.1:backend``; see the module's docstring. :meth:`close` stops it."""

    def __init__(self, host: str, port: int, backend: int):
        self.backend = backend
        self.sock = socket.create_server((host, port), reuse_port=False)
        self.port: int = self.sock.getsockname()[1]
        self.loop = asyncio.new_event_loop()
        self.ready = threading.Event()
        self.thread = threading.Thread(target=self._serve, name="foxglove-ws-compat", daemon=True)
        self.thread.start()
        self.ready.wait(10.0)

    def _serve(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.server = self.loop.run_until_complete(asyncio.start_server(self._client, sock=self.sock))
        self.ready.set()
        self.loop.run_forever()
        self.server.close()
        tasks = asyncio.all_tasks(self.loop)
        for task in tasks:  # the connections still open
            task.cancel()
        self.loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
        self.loop.close()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up: asyncio.StreamWriter | None = None
        try:
            head = await reader.readuntil(b"\r\n\r\n")
            if len(head) > HEAD_LIMIT:
                return
            head, renamed = rename_request(head)
            up_reader, up = await asyncio.open_connection("127.0.0.1", self.backend)
            up.write(head)
            answer = await up_reader.readuntil(b"\r\n\r\n")
            writer.write(rename_response(answer) if renamed else answer)
            await asyncio.gather(_pipe(reader, up), _pipe(up_reader, writer))
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
            pass  # a client or the server went away: its connection ends, nothing else does
        finally:
            for w in (writer, up):
                if w is not None:
                    w.close()

    def close(self) -> None:
        """Stop listening and end every connection; blocks until the thread has ended."""
        if self.thread.is_alive():
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(10.0)


async def _pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
    try:
        while data := await src.read(65536):
            dst.write(data)
            await dst.drain()
    finally:
        if dst.can_write_eof():
            try:
                dst.write_eof()
            except OSError:
                pass
