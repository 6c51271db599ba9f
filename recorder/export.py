"""``run.mcap`` beside a ``run.npz``, when the Foxglove SDK (the ``viz`` extra) is installed.

Every producer of a run directory (``tether simulate``, ``tether reproduce``, the recorder of
``tether run``) calls :func:`mcap_beside` right after writing ``run.npz``; the conversion itself is
:func:`recorder.viz.write_mcap`. Without ``foxglove-sdk`` the run file is written as before and a
one-line notice says why there is no ``run.mcap``.
"""

from __future__ import annotations

import logging
from pathlib import Path

from tether.mission import Mission
from tether.runfile import Run

log = logging.getLogger("tether")
_warned = False


def mcap_beside(run: Run, mission: Mission | None, npz: str | Path, scene_rate: float | None = None) -> Path | None:
    """Write ``run.mcap`` beside ``npz`` (the same name with ``.mcap``); returns its path, or None
    when the Foxglove SDK is not installed. ``scene_rate``: the 3D scene's rate [Hz] (None: the
    default, 0: every tick)."""
    global _warned
    try:
        from recorder import viz
    except ImportError as exc:
        if not _warned:
            log.warning("no run.mcap: the Foxglove SDK is not installed (pip install 'tether[viz]'): %s", exc)
            _warned = True
        return None
    rate = viz.SCENE_RATE if scene_rate is None else scene_rate
    return viz.write_mcap(run, mission, Path(npz).with_suffix(".mcap"), scene_rate=rate)
