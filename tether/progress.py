"""A one-line progress display for long commands (stderr only)."""

from __future__ import annotations

import sys
from collections.abc import Callable


class Progress:
    """A one-line progress display on stderr (redrawn on a terminal, every 10 % otherwise)."""

    def __init__(self) -> None:
        self.tty = sys.stderr.isatty()
        self.last: dict[str, int] = {}

    def __call__(self, k: int, n: int, label: str = "") -> None:
        pct = 100 * k // max(n, 1)
        if self.tty:
            sys.stderr.write(f"\r{label:>20} {pct:3d}% ({k}/{n})")
            if k >= n:
                sys.stderr.write("\n")
            sys.stderr.flush()
        elif pct // 10 != self.last.get(label, -1):
            self.last[label] = pct // 10
            sys.stderr.write(f"{label} {pct}%\n")


def labelled(progress: Callable[[int, int, str], None], label: str) -> Callable[[int, int], None]:
    """``progress`` reporting under ``label``: the ``(k, n)`` form the engines call."""
    return lambda k, n: progress(k, n, label)
