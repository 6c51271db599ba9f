"""The Foxglove view of a run: ``run.mcap`` beside ``run.npz``, and the live view (``--live``).

One converter for every producer: :func:`write_mcap` turns a finished :class:`~tether.runfile.Run`
into an MCAP file through the Foxglove SDK (``foxglove-sdk``, the ``viz`` extra); :class:`Live`
serves the same channels over the Foxglove WebSocket protocol while a run is being filled. Both log
through one :class:`View`, so a file and a live session carry the same topics, schemas and values.
The channels (``docs/foxglove.md``):

=====================  ======================  =========================================================
``/scene``             foxglove.SceneUpdate    vehicles (coloured by safety mode), the leader, the
                                               formation slots (leader + offset), payload and cables
                                               (coloured by tension), the geofence box
``/tf``                foxglove.FrameTransforms  world -> ``agent_<id>`` (attitude when recorded),
                                               ``leader``, ``payload``
``/agent/<id>``        tether.Agent (JSON)     per tick: ||xi||, xi, zeta, Kp, Kv, u, p, v, d, modes,
                                               links (age, delivery) and the runtime's own columns
``/leader``            tether.Leader (JSON)    the leader's p, v, a
``/payload``           tether.Payload (JSON)   payload p, v, cable tensions, slack events ([payload])
``/safety``            foxglove.Log            every safety event: the agents' supervisors' mode changes
                                               (name ``agent <id>``), the plants' watchdogs' mode
                                               changes and command rejections (name ``plant <id>``)
``/log``               foxglove.Log            the run's notes: what ran, divergence, gate rejections
=====================  ======================  =========================================================

Every other array and event of the run file is on the channels of :class:`recorder.export.Complete`
(``/run``, ``/run/static``, ``/link/<dst>/<src>``, ``/events/...``, and extra
``/agent/<id>`` fields), so that the file is the whole run.

Time: the log time (and every header stamp) of a sample of mission time t is ``epoch + t`` in
nanoseconds: a real-time run's tick 0 Unix time (``RunMeta.epoch_ns``), else :data:`EPOCH_NS`, so
that Foxglove's "seconds" clock reads 1000000000 + t. Mission time is the sample time
``t_k = k h`` of the run file (the simulator's and the lockstep clock's time; in real time the tick's
sample time). Time series are written at every tick; the 3D scene (``/scene``, ``/tf``) at up to
``scene_rate`` Hz (:data:`SCENE_RATE`; 0: every tick).

Only the recorder, ``sim`` and ``cli`` import this module; agents, leaders and plants never do.
"""

from __future__ import annotations

import collections
import gc
import json
import math
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import msgspec
import numpy as np

import foxglove
from foxglove import channels as fch
from foxglove import messages as fm
from foxglove.mcap import MCAPWriteOptions
from foxglove.websocket import ServerListener

from recorder import export
from recorder.export import EPOCH_NS, epoch_of
from tether import mission as ms
from tether.runfile import NO_SAMPLE, Run, missing_report
from tether.wire import SafetyEvent
SCENE_RATE = 25.0
"""Default rate of the 3D scene in a file [Hz] (time series are always at every tick)."""
GRAVITY = 9.81
ZSTD_LEVEL = 1
"""zstd level of the file's chunks: measured on 20 001 ticks of Section 4, level 1 writes in two thirds of
the CPU time of the SDK's default and makes a smaller file (16.7 MB against 18.0 MB; bench/recording.py)."""

MODE_COLOURS = {
    0: (0.20, 0.75, 0.30),  # FLYING: green
    1: (0.95, 0.75, 0.10),  # HOLD: amber
    2: (0.95, 0.45, 0.10),  # LAND: orange
    3: (0.55, 0.55, 0.55),  # LANDED: grey
    4: (0.90, 0.10, 0.10),  # ESTOP: red
}
NO_SAMPLE_COLOUR = (0.25, 0.25, 0.25)
LEADER_COLOUR = (0.20, 0.45, 0.95)
SLOT_COLOUR = (0.20, 0.45, 0.95)
PAYLOAD_COLOUR = (0.60, 0.35, 0.15)
GRAPH_COLOUR = (0.55, 0.75, 0.95)
TRAIL = 50
"""Scene frames of each vehicle's trail (2 s at the default 25 Hz)."""
LEADER = -1
"""The leader's index in :attr:`Layout.edges`."""
FENCE_COLOUR = (0.90, 0.20, 0.20)


def stamp(t: float, epoch_ns: int = EPOCH_NS) -> int:
    """The log time [ns] of mission time ``t`` [s] of a run whose tick 0 is at ``epoch_ns``
    (:func:`recorder.export.epoch_of`; the default: simulated time's fixed epoch)."""
    return epoch_ns + int(round(t * 1e9))


def _ts(ns: int) -> fm.Timestamp:
    return fm.Timestamp(ns // 10**9, ns % 10**9)


def _colour(rgb: Sequence[float], a: float = 1.0) -> fm.Color:
    return fm.Color(r=rgb[0], g=rgb[1], b=rgb[2], a=a)


def tension_colour(tension: float, nominal: float) -> tuple[float, float, float, float]:
    """A cable's colour: grey when slack (or unknown), green at no load rising through yellow to
    red at twice the nominal share ``nominal`` of the payload's weight and beyond."""
    if not math.isfinite(tension) or tension <= 0.0:
        return (0.6, 0.6, 0.6, 0.6)
    x = min(1.0, tension / (2.0 * nominal)) if nominal > 0 else 1.0
    return (min(1.0, 2.0 * x), min(1.0, 2.0 * (1.0 - x)), 0.1, 1.0)


def quaternions(rpy: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw ``(..., 3)`` [rad] (Z-Y-X) as quaternions ``(..., 4)`` (x, y, z, w);
    identity where NaN."""
    r, p, y = (0.5 * rpy[..., i] for i in range(3))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    q = np.stack([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
                  cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy], axis=-1)
    bad = ~np.all(np.isfinite(q), axis=-1)
    q[bad] = (0.0, 0.0, 0.0, 1.0)
    return q


def _vec_schema(title: str, dim: int) -> dict:
    return {"type": "array", "items": {"type": ["number", "null"]}, "minItems": dim, "maxItems": dim,
            "description": title}


def _num(desc: str) -> dict:
    return {"type": ["number", "null"], "description": desc}


def law_state_fields(run: Run) -> dict[str, str]:
    """The law's state variables of ``run`` by name, each with a description that gives its unit
    where the law declares one (``"s [m s]: the law's state variable s"``)."""
    units = run.meta.law_units or ("",) * len(run.meta.law_state)
    return {name: f"{name}{f' [{unit}]' if unit else ''}: the law's state variable {name}"
            for name, unit in zip(run.meta.law_state, units)}


class Layout:
    """What a run's view is made of: its agents, dimension, offsets, and which groups it has."""

    def __init__(self, run: Run, mission: ms.Mission | None):
        self.ids = [int(a) for a in run.agent_ids]
        self.n, self.dim = len(self.ids), run.p.shape[2]
        self.modes = tuple(run.meta.modes)
        self.law_state = law_state_fields(run)
        """The law's state variables by name, with the description of each (:func:`law_state_fields`)."""
        self.offsets = np.zeros((self.n, 3))
        self.edges: list[tuple[int, int]] = []
        """The communication graph's edges j -> i as (index of j, or LEADER; index of i) (none without the mission)."""
        self.fence = None
        self.nominal_tension = 0.0
        if mission is not None:
            by_id = {a.id: a for a in mission.agents}
            for i, aid in enumerate(self.ids):
                if aid in by_id:
                    self.offsets[i, : self.dim] = by_id[aid].offset
            self.fence = mission.safety.geofence
            index = {aid: i for i, aid in enumerate(self.ids)}
            self.edges = [(index.get(e.src, LEADER), index[e.dst]) for e in mission.edges if e.dst in index]
            if mission.payload is not None:
                self.nominal_tension = mission.payload.mass * GRAVITY / max(self.n, 1)
        pl = run.plant
        self.payload = pl.payload_p is not None
        self.tension = pl.tension is not None
        self.attitude = pl.attitude is not None
        lk = run.links
        self.link_src = None if lk is None else [[int(s) for s in row] for row in lk.src]
        self.link_delivery = lk is not None and lk.delivery is not None
        self.runtime = run.runtime is not None

    def agent_schema(self) -> dict:
        d = self.dim
        props = {
            "t": {"type": "number", "description": "mission time [s]"},
            "k": {"type": "integer", "description": "tick"},
            "xi_norm": _num("||xi_i|| [m]"),
            "xi": _vec_schema("formation error xi_i [m] (Eq. 8)", d),
            "zeta": _vec_schema("velocity error zeta_i [m/s] (Eq. 9)", d),
            "kp": _vec_schema("gain Kp", d),
            "kv": _vec_schema("gain Kv", d),
            "u": _vec_schema("command u_i [m/s^2]", d),
            "p": _vec_schema("position [m]", d),
            "v": _vec_schema("velocity [m/s]", d),
            "d": _vec_schema("disturbance [m/s^2] (null where unknown)", d),
            "safety_mode": {"type": "integer", "description": "supervisor mode code (-1: no sample)"},
            "safety_mode_name": {"type": "string"},
            "plant_mode": {"type": "integer", "description": "plant watchdog mode code (-1: no sample)"},
        }
        if self.law_state:
            props["law"] = {"type": "object", "description": "the law's state at t_k, by the law's names",
                            "properties": {name: _vec_schema(desc, d) for name, desc in self.law_state.items()}}
        if self.link_src is not None:
            link = {"src": {"type": "integer"}, "age": _num("age of j's sample when used [s]")}
            if self.link_delivery:
                link["delivery"] = _num("distinct samples received / sent, so far")
            props["links"] = {"type": "array", "items": {"type": "object", "properties": link}}
        if self.runtime:
            props["meas_age"] = _num("age of the own measurement when used [s]")
            props["drops"] = _num("messages dropped so far")
        return {"title": "tether.Agent", "type": "object", "properties": props}

    def leader_schema(self) -> dict:
        d = self.dim
        return {"title": "tether.Leader", "type": "object",
                "properties": {"t": {"type": "number"}, "k": {"type": "integer"},
                               "p": _vec_schema("position [m]", d), "v": _vec_schema("velocity [m/s]", d),
                               "a": _vec_schema("acceleration [m/s^2]", d)}}

    def payload_schema(self) -> dict:
        return {"title": "tether.Payload", "type": "object",
                "properties": {"t": {"type": "number"}, "k": {"type": "integer"},
                               "p": _vec_schema("position [m]", 3), "v": _vec_schema("velocity [m/s]", 3),
                               "tension": {"type": "array", "items": {"type": ["number", "null"]},
                                           "description": "cable tension per vehicle [N], agent order"},
                               "tension_max": _num("largest cable tension [N]"),
                               "slack_events": {"type": "array", "items": {"type": ["number", "null"]}}}}


class Rows:
    """Tick k of a run's arrays as Python lists: a chunk of ticks converted at once (files:
    :class:`recorder.export.Chunks`), or one tick at a time (live)."""

    NAMES = ("p", "v", "u", "xi", "zeta", "kp", "kv", "d", "leader_p", "leader_v", "leader_a")

    def __init__(self, run: Run, layout: Layout, whole: bool):
        self.run, self.layout, self.whole = run, layout, whole
        arrays = {name: getattr(run, name) for name in self.NAMES}
        arrays["xi_norm"] = None
        arrays["safety_mode"] = run.safety.safety_mode
        arrays["plant_mode"] = run.safety.plant_mode
        if layout.link_src is not None:
            assert run.links is not None  # the layout saw them
            arrays["link_age"] = run.links.age
            if layout.link_delivery:
                arrays["link_delivery"] = run.links.delivery
        if layout.runtime:
            assert run.runtime is not None
            arrays["meas_age"], arrays["drops"] = run.runtime.meas_age, run.runtime.drops
            arrays["plant_p"] = run.runtime.plant_p  # where the scene draws a vehicle without the agent's sample
        if layout.payload:
            arrays["payload_p"], arrays["payload_v"] = run.plant.payload_p, run.plant.payload_v
        if layout.tension:
            arrays["tension"], arrays["slack_events"] = run.plant.tension, run.plant.slack_events
        if layout.attitude:
            arrays["quat"] = None
        if layout.law_state:
            arrays["law_state"] = None
        self.arrays = arrays
        self.chunks = (export.Chunks(lambda k0, k1: {n: self._full(n, slice(k0, k1)) for n in arrays}, len(run.t))
                       if whole else None)

    def _full(self, name: str, k: slice | int | np.ndarray = slice(None)) -> np.ndarray:
        if name == "xi_norm":
            return np.linalg.norm(self.run.xi[k], axis=-1)
        if name == "law_state":  # (S, T, N, d) -> per tick (N, S, d)
            return np.moveaxis(self.run.law_state[:, k], 0, -2)
        if name == "quat":
            attitude = self.run.plant.attitude
            assert attitude is not None  # only in the layout when recorded
            return quaternions(attitude[k])
        return self.arrays[name][k]

    def at(self, k: int) -> dict[str, list]:
        if self.chunks is not None:
            return self.chunks.at(k)
        return {name: self._full(name, k).tolist() for name in self.arrays}


class View:
    """Logs a run's ticks, events and notes on the channels of one Foxglove context."""

    def __init__(self, ctx: foxglove.Context, layout: Layout, scene_every: int = 1,
                 run: Run | None = None, whole: bool = True):
        self.lay, self.scene_every = layout, max(1, int(scene_every))
        self.enc = msgspec.json.Encoder()
        L = layout
        self.epoch = EPOCH_NS if run is None else epoch_of(run)
        self.scene = fch.SceneUpdateChannel("/scene", context=ctx)
        self.tf = fch.FrameTransformsChannel("/tf", context=ctx)
        self.safety = fch.LogChannel("/safety", context=ctx)
        self.log = fch.LogChannel("/log", context=ctx)
        schema = L.agent_schema()

        def channel(topic: str, sch: dict) -> Callable[[bytes, int], None]:
            return foxglove.Channel(topic, schema=sch, context=ctx).base.log

        # the rest of the run file: every array and event not on the channels above (recorder/export.py)
        self.complete = (None if run is None else
                         export.Complete(run, channel, set(schema["properties"]) | set(Rows.NAMES), whole))
        if self.complete is not None:
            schema["properties"].update(self.complete.agent_schema())
        self.agents = [foxglove.Channel(f"/agent/{aid}", schema=schema, context=ctx).base for aid in L.ids]
        self.leader = foxglove.Channel("/leader", schema=L.leader_schema(), context=ctx).base
        self.payload = (foxglove.Channel("/payload", schema=L.payload_schema(), context=ctx).base
                        if L.payload else None)
        # objects that never change, built once and shared by every scene message
        self.ident = fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
        self.vsize = fm.Vector3(x=0.15, y=0.15, z=0.15)
        self.lsize = fm.Vector3(x=0.2, y=0.2, z=0.2)
        self.psize = fm.Vector3(x=0.12, y=0.12, z=0.12)
        self.mode_colour = {c: _colour(rgb) for c, rgb in MODE_COLOURS.items()}
        self.nosample = _colour(NO_SAMPLE_COLOUR)
        self.leader_colour = _colour(LEADER_COLOUR)
        self.slot_colour = _colour(SLOT_COLOUR, 0.25)
        self.payload_colour = _colour(PAYLOAD_COLOUR)
        self.white = _colour((1.0, 1.0, 1.0))
        self.frames = [f"agent_{aid}" for aid in L.ids]
        self.trails: list[collections.deque[fm.Point3]] = [collections.deque(maxlen=TRAIL) for _ in L.ids]
        self.graph_colour = _colour(GRAPH_COLOUR, 0.5)
        self.fence = self._fence_entity() if L.fence is not None else None

    # ------------------------------------------------------------------ scene
    def _v3(self, p: Sequence[float], dz: float = 0.0) -> fm.Vector3:
        z = p[2] if len(p) > 2 else 0.0
        return fm.Vector3(x=_f(p[0]), y=_f(p[1]), z=_f(z) + dz)

    def _point(self, p: Sequence[float]) -> fm.Point3:
        return fm.Point3(x=_f(p[0]), y=_f(p[1]), z=_f(p[2]) if len(p) > 2 else 0.0)

    def _pose(self, p: Sequence[float]) -> fm.Pose:
        return fm.Pose(position=self._v3(p), orientation=self.ident)

    def _fence_entity(self) -> fm.SceneEntity:
        f = self.lay.fence
        assert f is not None  # called only with a fence
        lo = list(f.min) + [0.0] * (3 - len(f.min))
        hi = list(f.max) + [0.0] * (3 - len(f.max))
        corners = [(x, y, z) for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        edges = [(a, b) for a in range(8) for b in range(a + 1, 8)
                 if sum(corners[a][i] != corners[b][i] for i in range(3)) == 1]
        pts = [fm.Point3(x=corners[i][0], y=corners[i][1], z=corners[i][2]) for e in edges for i in e]
        line = fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineList, pose=fm.Pose(orientation=self.ident),
                                thickness=2.0, scale_invariant=True, points=pts, color=_colour(FENCE_COLOUR, 0.8))
        return fm.SceneEntity(frame_id="world", id="geofence", lines=[line],
                              metadata=[fm.KeyValuePair(key="action", value=f.action)])

    def _scene(self, k: int, ns: int, r: dict) -> None:
        L = self.lay
        stamp_ = _ts(ns)
        modes = r["safety_mode"]
        spheres, texts = [], []
        for i, aid in enumerate(L.ids):
            p = _where(r, i)
            if p is None:  # neither the agent nor its plant said where it is: not drawn
                continue
            colour = self.mode_colour.get(modes[i], self.nosample)
            spheres.append(fm.SpherePrimitive(pose=self._pose(p), size=self.vsize, color=colour))
            label = str(aid) if modes[i] == 0 else f"{aid} {_name(L.modes, modes[i])}"
            texts.append(fm.TextPrimitive(pose=fm.Pose(position=self._v3(p, 0.15), orientation=self.ident),
                                          billboard=True, font_size=14.0, scale_invariant=True, color=self.white,
                                          text=label))
        lp = r["leader_p"]
        lead3 = [lp[j] if j < L.dim else 0.0 for j in range(3)]
        slots = [fm.CubePrimitive(pose=fm.Pose(position=fm.Vector3(x=_f(lead3[0] + o[0]), y=_f(lead3[1] + o[1]),
                                                                   z=_f(lead3[2] + o[2])), orientation=self.ident),
                                  size=self.vsize, color=self.slot_colour) for o in L.offsets.tolist()]
        where = [_where(r, i) for i in range(L.n)]
        trails = []
        for i, p in enumerate(where):
            if p is not None:
                self.trails[i].append(self._point(p))
            if len(self.trails[i]) > 1:
                trails.append(fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineStrip, pose=fm.Pose(orientation=self.ident),
                                               thickness=1.5, scale_invariant=True, points=list(self.trails[i]),
                                               color=_colour(MODE_COLOURS.get(modes[i], NO_SAMPLE_COLOUR), 0.5)))
        graph = []
        for j, i in L.edges:  # j -> i: i hears j
            src, dst = (lp if j == LEADER else where[j]), where[i]
            if src is not None and dst is not None:
                graph += [self._point(src), self._point(dst)]
        ents = [
            fm.SceneEntity(timestamp=stamp_, frame_id="world", id="vehicles", spheres=spheres, texts=texts),
            fm.SceneEntity(timestamp=stamp_, frame_id="world", id="trails", lines=trails),
            fm.SceneEntity(timestamp=stamp_, frame_id="world", id="graph", lines=[fm.LinePrimitive(
                type=fm.LinePrimitiveLineType.LineList, pose=fm.Pose(orientation=self.ident), thickness=1.0,
                scale_invariant=True, points=graph, color=self.graph_colour)] if graph else []),
            fm.SceneEntity(timestamp=stamp_, frame_id="world", id="leader",
                           spheres=[fm.SpherePrimitive(pose=self._pose(lp), size=self.lsize, color=self.leader_colour)],
                           texts=[fm.TextPrimitive(pose=fm.Pose(position=self._v3(lp, 0.2), orientation=self.ident),
                                                   billboard=True, font_size=14.0, scale_invariant=True,
                                                   color=self.white, text="leader")]),
            fm.SceneEntity(timestamp=stamp_, frame_id="world", id="slots", cubes=slots),
        ]
        if L.payload:
            pp = r["payload_p"]
            prims: dict[str, Any] = {"spheres": [fm.SpherePrimitive(pose=self._pose(pp), size=self.psize, color=self.payload_colour)]}
            if L.tension:
                pts, cols = [], []
                top = fm.Point3(x=_f(pp[0]), y=_f(pp[1]), z=_f(pp[2]))
                for i in range(L.n):
                    rgba = tension_colour(r["tension"][i], L.nominal_tension)
                    c = fm.Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])
                    q = r["p"][i]
                    pts += [fm.Point3(x=_f(q[0]), y=_f(q[1]), z=_f(q[2])), top]
                    cols += [c, c]
                prims["lines"] = [fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineList,
                                                   pose=fm.Pose(orientation=self.ident), thickness=2.0,
                                                   scale_invariant=True, points=pts, colors=cols)]
            ents.append(fm.SceneEntity(timestamp=stamp_, frame_id="world", id="payload", **prims))
        if self.fence is not None:
            ents.append(self.fence)
        self.scene.log(fm.SceneUpdate(entities=ents), log_time=ns)
        quat = r.get("quat")
        tfs = []
        for i in range(L.n):
            p = _where(r, i)
            if p is None:
                continue
            q = quat[i] if quat is not None else None
            rot = self.ident if q is None else fm.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])
            tfs.append(fm.FrameTransform(timestamp=stamp_, parent_frame_id="world", child_frame_id=self.frames[i],
                                         translation=self._v3(p), rotation=rot))
        tfs.append(fm.FrameTransform(timestamp=stamp_, parent_frame_id="world", child_frame_id="leader",
                                     translation=self._v3(lp), rotation=self.ident))
        if L.payload:
            tfs.append(fm.FrameTransform(timestamp=stamp_, parent_frame_id="world", child_frame_id="payload",
                                         translation=self._v3(r["payload_p"]), rotation=self.ident))
        self.tf.log(fm.FrameTransforms(transforms=tfs), log_time=ns)

    # ------------------------------------------------------------------ ticks
    def tick(self, k: int, t: float, r: dict, scene: bool | None = None) -> None:
        """Log tick ``k`` (mission time ``t``) from its rows ``r`` (:meth:`Rows.at`)."""
        L, enc = self.lay, self.enc
        ns = stamp(t, self.epoch)
        modes, pmodes = r["safety_mode"], r["plant_mode"]
        extra = self.complete.agent_fields(k) if self.complete is not None else None
        for i, ch in enumerate(self.agents):
            msg = {"t": t, "k": k, "xi_norm": r["xi_norm"][i], "xi": r["xi"][i], "zeta": r["zeta"][i],
                   "kp": r["kp"][i], "kv": r["kv"][i], "u": r["u"][i], "p": r["p"][i], "v": r["v"][i],
                   "d": r["d"][i], "safety_mode": modes[i], "safety_mode_name": _name(L.modes, modes[i]),
                   "plant_mode": pmodes[i]}
            if L.link_src is not None:
                ages = r["link_age"][i]
                dl = r["link_delivery"][i] if L.link_delivery else None
                msg["links"] = [{"src": s, "age": ages[n], **({"delivery": dl[n]} if dl is not None else {})}
                                for n, s in enumerate(L.link_src[i]) if s != 0]
            if L.runtime:
                msg["meas_age"], msg["drops"] = r["meas_age"][i], r["drops"][i]
            if L.law_state:
                msg["law"] = dict(zip(L.law_state, r["law_state"][i]))
            if extra is not None:
                msg.update(extra[i])
            ch.log(enc.encode(msg), ns)
        self.leader.log(enc.encode({"t": t, "k": k, "p": r["leader_p"], "v": r["leader_v"], "a": r["leader_a"]}), ns)
        if self.payload is not None:
            msg = {"t": t, "k": k, "p": r["payload_p"], "v": r["payload_v"]}
            if L.tension:
                ten = r["tension"]
                finite = [x for x in ten if x == x]
                msg.update(tension=ten, tension_max=max(finite) if finite else None, slack_events=r["slack_events"])
            self.payload.log(enc.encode(msg), ns)
        if self.complete is not None:
            self.complete.tick(k, ns)
        if scene if scene is not None else k % self.scene_every == 0:
            self._scene(k, ns, r)

    def end_of_record(self, k: int, t: float, r: dict, last: float) -> None:
        """The scene at tick ``k`` (time ``t``), the first the record lacks after its last (at time
        ``last``): every vehicle where it was last heard, drawn as "no sample" (``r``'s modes, −1),
        and a note on ``/log``."""
        self._scene(k, stamp(t, self.epoch), r)
        self.note(t, f"no sample after t = {last:.2f} s: the vehicles' modes and positions from here on "
                     "are not in this record", fm.LogLevel.Warning)

    def event(self, e: SafetyEvent, origin: str = "agent") -> None:
        """A safety event on ``/safety``, named by its origin (``agent <id>``: the supervisor's;
        ``plant <id>``: the plant's watchdog, whose events include command rejections without a
        mode change, ``src == dst``)."""
        ns = stamp(e.t, self.epoch)
        dst = _name(self.lay.modes, e.dst)
        level = (fm.LogLevel.Error if dst == "ESTOP" else
                 fm.LogLevel.Warning if dst in ("HOLD", "LAND") or e.src == e.dst else fm.LogLevel.Info)
        change = f"{dst}" if e.src == e.dst else f"{_name(self.lay.modes, e.src)} -> {dst}"
        text = f"t = {e.t:.3f} s: {origin} {e.vehicle}: {change}: {e.reason}"
        self.safety.log(fm.Log(timestamp=_ts(ns), level=level, message=text, name=f"{origin} {e.vehicle}"),
                        log_time=ns)
        if self.complete is not None:
            self.complete.event("events" if origin == "agent" else "plant_events", e, ns, self.lay.modes)

    def launcher(self, event: dict[str, Any]) -> None:
        """One of the launcher's events (``events.json``: ``t``, ``who``, ``what``, ``why``) on
        ``/events/launcher`` and, as text, on ``/log`` (name ``launcher``)."""
        t = event["t"] if event["t"] is not None else 0.0  # before tick 0: at tick 0
        ns = stamp(t, self.epoch)
        if self.complete is not None:
            self.complete.launcher(event, ns)
        level = fm.LogLevel.Warning if event["what"] != "back" else fm.LogLevel.Info
        self.log.log(fm.Log(timestamp=_ts(ns), level=level, name="launcher",
                            message=f"t = {t:.3f} s: {event['who']}: {event['what']}: {event['why']}"), log_time=ns)

    def note(self, t: float, text: str, level: fm.LogLevel = fm.LogLevel.Info, name: str = "tether") -> None:
        """A note on ``/log``."""
        ns = stamp(t, self.epoch)
        self.log.log(fm.Log(timestamp=_ts(ns), level=level, message=text, name=name), log_time=ns)


def _f(x: float) -> float:
    """A coordinate for a scene primitive (a NaN component of a position otherwise known: 0)."""
    return x if x == x else 0.0


def _where(r: dict, i: int) -> list[float] | None:
    """Where vehicle ``i`` is at a tick of rows ``r``: the agent's position, else its plant's own
    measurement (an agent killed or silent: its plant holds and lands), else None (not drawn;
    never the origin)."""
    p = r["p"][i]
    if all(x == x for x in p):
        return p
    plant = r.get("plant_p")
    if plant is not None and all(x == x for x in plant[i]):
        return plant[i]
    return None


def _name(modes: Sequence[str], code: int) -> str:
    return modes[code] if 0 <= code < len(modes) else ("no sample" if code == NO_SAMPLE else str(code))


def _mission_of(run: Run, mission: ms.Mission | None) -> ms.Mission | None:
    if mission is not None or not run.meta.mission_text:
        return mission
    try:
        return ms.loads(run.meta.mission_text)
    except Exception:  # an old or foreign mission text: the scene loses offsets and fence, nothing else
        return None


def scene_every(rate: float, scene_rate: float | None) -> int:
    """Ticks between scene messages for a control rate and a scene rate (0 or None: every tick)."""
    if not scene_rate or scene_rate <= 0 or scene_rate >= rate:
        return 1
    return max(1, int(round(rate / scene_rate)))


def _opening_notes(view: View, run: Run) -> None:
    m = run.meta
    view.note(0.0, f"mission {m.mission!r}: {m.source}, law {m.law}, {m.rate:g} Hz, {m.steps} steps, "
                   f"seed {m.seed}; {len(run.agent_ids)} agents {list(map(int, run.agent_ids))}")


def heard(run: Run) -> np.ndarray:
    """(T,) bool: the ticks of ``run`` that hold any sample (a finite time, and the leader's sample or
    a mode); a recorder's run stopped or cut short has none beyond its last, and none while it heard
    nothing. The engines' runs hold every tick."""
    return (np.isfinite(run.t) & (np.isfinite(run.leader_p).all(axis=1)
                                  | (run.safety.safety_mode != NO_SAMPLE).any(axis=1)
                                  | (run.safety.plant_mode != NO_SAMPLE).any(axis=1)))


def _events(run: Run) -> list[tuple[SafetyEvent, str]]:
    """Every safety event of ``run`` with its origin, in order of (tick, vehicle, time, origin)."""
    both = [(e, "agent") for e in run.safety.events] + [(e, "plant") for e in run.safety.plant_events]
    return sorted(both, key=lambda eo: (eo[0].k, eo[0].vehicle, eo[0].t, eo[1]))


def _closing_notes(view: View, run: Run) -> None:
    m = run.meta
    written = run.t[heard(run)]
    t_end = float(written[-1]) if len(written) else 0.0  # the last tick written (a stopped run's hold none after it)
    if m.diverged_at is not None:
        view.note(m.diverged_at, f"the run diverged at t = {m.diverged_at:g} s and was stopped", fm.LogLevel.Error)
    s = run.safety
    if s.gate_counts is not None and s.gate_reasons is not None:
        for i, aid in enumerate(run.agent_ids):
            counts = {str(r): int(c) for r, c in zip(s.gate_reasons, s.gate_counts[i]) if c}
            if counts:
                view.note(t_end, f"agent {aid}: the gate rejected " + ", ".join(f"{c} {r}" for r, c in counts.items()),
                          fm.LogLevel.Warning, name=f"agent {aid}")
    if m.complete is not None:
        view.note(t_end, f"recorded {m.samples_recorded} of {m.samples_expected} samples"
                         + ("" if m.complete else " (incomplete)"),
                  fm.LogLevel.Info if m.complete else fm.LogLevel.Warning)
    for line in missing_report(run):  # what the file lacks, said rather than shown as stale values
        view.note(t_end, f"missing: {line}", fm.LogLevel.Warning)
    view.note(t_end, f"end of run at t = {t_end:g} s")


def write_mcap(run: Run, mission: ms.Mission | None, path: str | Path, scene_rate: float | None = SCENE_RATE) -> Path:
    """Write ``run`` as an MCAP file at ``path`` (atomically); returns it. ``mission`` gives the
    offsets, geofence and payload of the scene (None: read from the run's mission text)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mission = _mission_of(run, mission)
    layout = Layout(run, mission)
    tmp = path.with_name(path.name + ".part")
    collecting = gc.isenabled()
    gc.disable()  # millions of short-lived lists and dicts: the cyclic collector would cost a third
    ctx = foxglove.Context()
    writer = foxglove.open_mcap(tmp, allow_overwrite=True, context=ctx,
                                writer_options=MCAPWriteOptions(compression_threads=0, compression_level=ZSTD_LEVEL))
    try:
        view = View(ctx, layout, scene_every(run.meta.rate, scene_rate), run=run)
        writer.write_metadata("tether", {
            "mission": run.meta.mission, "source": run.meta.source, "law": run.meta.law,
            "rate_hz": f"{run.meta.rate:g}", "steps": str(run.meta.steps), "epoch_ns": str(view.epoch),
            "clock": "unix" if run.meta.epoch_ns is not None else "simulated",
            "scene_every": str(view.scene_every), "modes": ",".join(layout.modes),
            "run_meta": msgspec.json.encode(msgspec.structs.replace(run.meta, mission_text=None)).decode()})
        if run.meta.mission_text:
            writer.attach(log_time=view.epoch, create_time=view.epoch, name="mission.toml",
                          media_type="application/toml", data=run.meta.mission_text.encode())
        rows = Rows(run, layout, whole=True)
        events = _events(run)
        ev = 0
        _opening_notes(view, run)
        assert view.complete is not None  # made with the run
        view.complete.start(view.epoch)
        for said in export.launcher_events(path.with_suffix(".npz")):
            view.launcher(said)
        times = run.t.tolist()
        written = heard(run)
        ticks = np.flatnonzero(written).tolist()
        last = ticks[-1] if ticks else -1
        for k in ticks:  # an unrecorded tick (a run stopped early, a recorder frozen) is left out
            while ev < len(events) and events[ev][0].k <= k:
                view.event(*events[ev])
                ev += 1
            view.tick(k, times[k], rows.at(k), scene=(k % view.scene_every == 0 or k == last))
        for e, origin in events[ev:]:
            view.event(e, origin)
        if 0 <= last < len(times) - 1:
            # the record stops before the run's end (a recorder stopped, frozen or killed): the scene's
            # last frame says so rather than show the last modes heard as if they still held
            gone = dict(rows.at(last))
            gone["safety_mode"] = [NO_SAMPLE] * len(run.agent_ids)
            gone["plant_mode"] = [NO_SAMPLE] * len(run.agent_ids)
            after = times[last] + 1.0 / run.meta.rate
            view.end_of_record(last + 1, after, gone, times[last])
        _closing_notes(view, run)
    finally:
        writer.close()
        if collecting:
            gc.enable()
    tmp.replace(path)
    return path


class _ReadOnly(ServerListener):
    """The live view's parameters (:func:`recorder.export.parameters`): a client reads them, and a
    client's set changes nothing (the server answers with the values the run flies). Called on the
    SDK's threads; it only reads a dict built once."""

    def __init__(self, values: dict[str, Any]):
        self.values = values

    def _params(self, names: Sequence[str]) -> list[foxglove.Parameter]:
        return [foxglove.Parameter(n, value=self.values[n]) for n in names if n in self.values]

    def on_get_parameters(self, client: Any, param_names: list[str], request_id: str | None = None
                          ) -> list[foxglove.Parameter]:
        return self._params(param_names or sorted(self.values))

    def on_set_parameters(self, client: Any, parameters: list[foxglove.Parameter], request_id: str | None = None
                          ) -> list[foxglove.Parameter]:
        return self._params([p.name for p in parameters])


class Live:
    """The live view: a Foxglove WebSocket server serving a run's channels as it is filled.

    Pass :meth:`tick` as the simulator's ``on_tick``; ``speed`` > 0 paces the run to that many
    mission seconds per wall second (so that a person can watch it), 0 lets it run as fast as it
    computes. The scene is sent at every tick up to ``scene_rate`` Hz."""

    def __init__(self, port: int = 8765, host: str = "127.0.0.1", speed: float = 1.0,
                 mission: ms.Mission | None = None, scene_rate: float | None = SCENE_RATE,
                 sleep: Callable[[float], None] = time.sleep):
        from recorder import wscompat

        self.ctx = foxglove.Context()
        # the SDK's server on a loopback port of its own; the public port is the shim's, which offers
        # both names of the protocol (recorder/wscompat.py)
        self.params = _ReadOnly(export.parameters(mission))
        self.server = foxglove.start_server(name="tether", host="127.0.0.1", port=0, context=self.ctx,
                                            capabilities=[foxglove.Capability.Time, foxglove.Capability.Parameters],
                                            server_listener=self.params)
        try:
            self.shim = wscompat.Shim(host, port, self.server.port)
        except OSError:
            self.server.stop()
            raise
        # None: the default rate, as in a file (0: every tick)
        self.scene_rate = SCENE_RATE if scene_rate is None else scene_rate
        self.speed, self.mission, self.sleep = speed, mission, sleep
        self.view: View | None = None
        self.rows: Rows | None = None
        self.wall0 = 0.0
        self.events = 0
        self.plant_events = 0

    @property
    def port(self) -> int:
        """The public port Foxglove clients connect to."""
        return self.shim.port

    def tick(self, run: Run, k: int, events: list[SafetyEvent] | None = None,
             plant_events: list[SafetyEvent] | None = None) -> None:
        """Log tick ``k`` of ``run``; the safety events are ``run.safety.events`` and
        ``run.safety.plant_events`` unless ``events`` and ``plant_events`` (lists that only grow:
        the recorder's, while the run is being filled) are given."""
        if self.view is None:
            layout = Layout(run, _mission_of(run, self.mission))
            self.view = View(self.ctx, layout, scene_every(run.meta.rate, self.scene_rate), run=run, whole=False)
            assert self.view.complete is not None  # made with the run
            self.view.complete.start(self.view.epoch)
            self.rows = Rows(run, layout, whole=False)
            _opening_notes(self.view, run)
            self.wall0 = time.monotonic()
        t = float(run.t[k])
        if self.speed > 0:
            ahead = t / self.speed - (time.monotonic() - self.wall0)
            if ahead > 0:
                self.sleep(ahead)
        if events is None:
            events = run.safety.events
        if plant_events is None:
            plant_events = run.safety.plant_events
        while self.events < len(events):
            self.view.event(events[self.events])
            self.events += 1
        while self.plant_events < len(plant_events):
            self.view.event(plant_events[self.plant_events], "plant")
            self.plant_events += 1
        assert self.rows is not None  # set by start()
        self.view.tick(k, t, self.rows.at(k))
        self.server.broadcast_time(stamp(t, self.view.epoch))

    def finish(self, run: Run) -> None:
        if self.view is not None:
            _closing_notes(self.view, run)

    def close(self) -> None:
        self.shim.close()
        self.server.stop()


__all__ = ["EPOCH_NS", "SCENE_RATE", "Layout", "Live", "View", "scene_every", "stamp", "write_mcap"]


def layout(agent_ids: Sequence[int] = (1, 2, 3, 4), dim: int = 2) -> str:
    """The Foxglove layout of ``docs/foxglove/tether.json`` for these agents: the 3D scene
    (world frame), ||xi_i||, Kp and Kv plots, the safety events and the run's log."""
    import foxglove.layouts as fl

    def plot(title: str, paths: list[tuple[str, str]]) -> fl.PlotPanel:
        return fl.PlotPanel(title=title, config=fl.PlotConfig(
            paths=[fl.PlotSeries(value=v, label=lab, timestamp_method="receiveTime") for v, lab in paths],
            show_legend=True, legend_display="floating"))

    ids = list(agent_ids)
    axes = "xyz"
    three_d = fl.ThreeDeePanel(title="formation", config=fl.ThreeDeeConfig(
        follow_tf="world", topics={"/scene": fl.BaseRendererSceneUpdateTopicSettings(visible=True)}))
    plots = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(content=plot("||xi_i|| [m]", [(f"/agent/{a}.xi_norm", f"agent {a}") for a in ids])),
        fl.SplitItem(content=plot("Kp", [(f"/agent/{a}.kp[{j}]", f"{a}{axes[j]}") for a in ids for j in range(dim)])),
        fl.SplitItem(content=plot("Kv", [(f"/agent/{a}.kv[{j}]", f"{a}{axes[j]}") for a in ids for j in range(dim)])),
        fl.SplitItem(content=plot("safety mode", [(f"/agent/{a}.safety_mode", f"agent {a}") for a in ids])),
    ])
    logs = fl.SplitContainer(direction="row", items=[
        fl.SplitItem(content=fl.LogPanel(title="safety events", config=fl.LogConfig(topic_to_render="/safety"))),
        fl.SplitItem(content=fl.LogPanel(title="run log", config=fl.LogConfig(topic_to_render="/log"))),
    ])
    left = fl.SplitContainer(direction="column", items=[fl.SplitItem(proportion=3, content=three_d),
                                                         fl.SplitItem(proportion=1, content=logs)])
    root = fl.SplitContainer(direction="row", items=[fl.SplitItem(proportion=3, content=left),
                                                     fl.SplitItem(proportion=2, content=plots)])
    return json.dumps(export.app_layout(json.loads(fl.Layout(content=root).to_json())), indent=2)
