"""Small helpers shared by the tests that drive real processes."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest


def wait_until(ready: Callable[[], Any], timeout: float, what: str, poll: float = 0.05) -> Any:
    """Poll ``ready()`` until it returns something truthy (returned); fail naming ``what`` after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        value = ready()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"waited {timeout:g} s for {what}")
        time.sleep(poll)


def read(path: Path) -> str:
    """A log file's text so far ('' while it does not exist)."""
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""
