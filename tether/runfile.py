"""Run files: one ``run.npz`` per run, written by the reference simulator and by the runtime's recorder.

Layout (every array float64 unless said; T samples, N agents, d dimensions; SI units, world frame):

=================  ===========  ====================================================================
``t``              (T,)         sample time t_k = k h [s]
``agent_ids``      (N,) int64   agent ids, in the order of the agent axis
``p`` ``v``        (T, N, d)    position [m], velocity [m/s] at t_k
``a``              (T, N, d)    measured acceleration shared with neighbours at t_k [m/s^2]
``u``              (T, N, d)    command computed at t_k and held over [t_k, t_k+h) [m/s^2]
``xi`` ``zeta``    (T, N, d)    formation error [m] (Eq. 8), velocity error [m/s] (Eq. 9) at t_k
``kp`` ``kv``      (T, N, d)    gains used for u at t_k
``d``              (T, N, d)    disturbance d(t_k) [m/s^2] (NaN where the recorder cannot know it)
``leader_p/v/a``   (T, d)       the virtual leader's state at t_k
``meta``           () str       JSON: mission name and text, source, law, rate, version
=================  ===========  ====================================================================

Optional arrays (present in runtime recordings): ``link_*`` per-agent link statistics, documented
in ``docs/runfile.md``. A run file opens with nothing but numpy: ``numpy.load("run.npz")``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

FORMAT_VERSION = 1
SERIES = ("p", "v", "a", "u", "xi", "zeta", "kp", "kv", "d")


@dataclass
class Run:
    t: np.ndarray
    agent_ids: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    u: np.ndarray
    xi: np.ndarray
    zeta: np.ndarray
    kp: np.ndarray
    kv: np.ndarray
    d: np.ndarray
    leader_p: np.ndarray
    leader_v: np.ndarray
    leader_a: np.ndarray
    meta: dict = field(default_factory=dict)
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    @classmethod
    def empty(cls, samples: int, agent_ids: list[int], dim: int, meta: dict) -> "Run":
        n = len(agent_ids)
        series = {name: np.full((samples, n, dim), np.nan) for name in SERIES}
        return cls(
            t=np.full(samples, np.nan),
            agent_ids=np.array(agent_ids, dtype=np.int64),
            leader_p=np.full((samples, dim), np.nan),
            leader_v=np.full((samples, dim), np.nan),
            leader_a=np.full((samples, dim), np.nan),
            meta=dict(meta),
            **series,
        )

    def save(self, path: str | Path) -> Path:
        """Write ``path`` (a ``.npz``) atomically; returns it."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {name: getattr(self, name) for name in ("t", "agent_ids", *SERIES, "leader_p", "leader_v", "leader_a")}
        arrays.update(self.extra)
        meta = dict(self.meta, format_version=FORMAT_VERSION)
        tmp = path.with_name(path.name + ".part")
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, meta=np.array(json.dumps(meta)), **arrays)
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "Run":
        path = Path(path)
        if path.is_dir():
            path = path / "run.npz"
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            known = {"t", "agent_ids", *SERIES, "leader_p", "leader_v", "leader_a", "meta"}
            extra = {k: z[k] for k in z.files if k not in known}
            return cls(meta=meta, extra=extra, **{k: z[k] for k in known - {"meta"}})
