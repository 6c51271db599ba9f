"""A one-line progress display for long commands (stderr only), with rate and ETA."""

from __future__ import annotations

import sys
import time
from typing import Callable, TextIO


def _duration(s: float) -> str:
    """``42s``, ``3m05s``, ``1h02m``."""
    s = max(0.0, s)
    if s < 60:
        return f"{s:.0f}s"
    if s < 3600:
        return f"{int(s // 60)}m{int(s % 60):02d}s"
    return f"{int(s // 3600)}h{int(s % 3600 // 60):02d}m"


def _rate(r: float) -> str:
    """Ticks per second, short: ``850/s``, ``12.3k/s``, ``1.2M/s``."""
    if r >= 1e6:
        return f"{r / 1e6:.1f}M/s"
    if r >= 1e4:
        return f"{r / 1e3:.1f}k/s"
    if r >= 100:
        return f"{r:.0f}/s"
    if r < 0.1:  # slow work (a study's cells): per minute, not 0.0/s
        return f"{r * 60:.2g}/min"
    return f"{r:.1f}/s"


class _Track:
    __slots__ = ("t0", "k0", "decade")

    def __init__(self, t0: float, k0: int) -> None:
        self.t0, self.k0, self.decade = t0, k0, -1


class Progress:
    """A one-line progress display on stderr (redrawn on a terminal, a line every 10 % otherwise),
    with the rate (ticks per second of wall time since the label's first call) and the ETA."""

    def __init__(self, stream: TextIO | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty()
        self.clock = clock
        self.tracks: dict[str, _Track] = {}

    def status(self, k: int, n: int, label: str = "", note: str = "") -> str:
        """The text of the display for ``k`` of ``n`` done (also starts the label's clock), ``note``
        (e.g. failures and workers) after it."""
        now = self.clock()
        tr = self.tracks.get(label)
        if tr is None:
            tr = self.tracks[label] = _Track(now, k)
        pct = 100 * k // max(n, 1)
        text = f"{pct:3d}% ({k}/{n})"
        elapsed = now - tr.t0
        if k > tr.k0 and elapsed > 0:
            rate = (k - tr.k0) / elapsed
            text += f" {_rate(rate)}"
            text += f" elapsed {_duration(elapsed)}" if k >= n else f" ETA {_duration((n - k) / rate)}"
        return f"{text} {note}" if note else text

    def __call__(self, k: int, n: int, label: str = "", note: str = "") -> None:
        text = self.status(k, n, label, note)
        tr = self.tracks[label]
        pct = 100 * k // max(n, 1)
        if self.tty:
            self.stream.write(f"\r{label:>20} {text}\x1b[K")
            if k >= n:
                self.stream.write("\n")
            self.stream.flush()
        elif pct // 10 != tr.decade:
            tr.decade = pct // 10
            self.stream.write(f"{label} {text.lstrip()}\n")
            self.stream.flush()


def labelled(progress: Callable[[int, int, str], None], label: str) -> Callable[[int, int], None]:
    """``progress`` reporting under ``label``: the ``(k, n)`` form the engines call."""
    return lambda k, n: progress(k, n, label)
