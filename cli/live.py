"""``--live [PORT]`` of ``tether simulate``, ``run`` and ``record``: the port checked before anything starts."""

from __future__ import annotations

import errno
import socket

DEFAULT_PORT = 8765


def port_problem(port: int | None, host: str = "127.0.0.1") -> str | None:
    """Why ``--live PORT`` cannot serve on ``host`` now (out of range, in use, not allowed), or
    None. The check binds the port and lets it go; the server binds it again moments later."""
    if port is None:
        return None
    if not 1 <= port <= 65535:
        return (f"--live: {port} is not a TCP port; give one in 1..65535, e.g. --live {DEFAULT_PORT} "
                "(or --live alone for the default)")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server does: TIME_WAIT is no conflict
        try:
            s.bind((host, port))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                return (f"--live: port {port} on {host} is in use (another program, or another live view, "
                        f"listens there); give a free port, e.g. --live {port + 1 if port < 65535 else 8765}")
            return (f"--live: cannot listen on {host}:{port} ({exc.strerror or exc}); give a port above 1023 "
                    f"that this user may open, e.g. --live {DEFAULT_PORT}")
    return None
