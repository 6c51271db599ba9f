"""The fleet file: what a lab keeps about its Crazyflies, one TOML file beside its missions. Pure
(no I/O beyond reading the file in :func:`load`).

A mission names its fleet file (``fleet = "lab.toml"``, relative to the mission file); each
``crazyflie`` plant of the mission is then the fleet's vehicle with the same URI, and flies with that
vehicle's mass, firmware parameters, position source and pre-flight limits (``docs/lab.md``)::

    version = 1

    [types.cf21_mocap]                  # settings shared by vehicles of one build
    mass = 0.032                        # [kg], a vehicle's own `mass` overrides it
    position_source = "mocap"           # "onboard" (Lighthouse, Loco, flow deck) or "mocap" (extpos)
    params = { "stabilizer.estimator" = 2, "stabilizer.controller" = 1, "locSrv.extPosStdDev" = 0.008 }

    [health]                            # pre-flight limits (plant/preflight.py)
    battery_min = 3.8                   # [V] refuse take-off below
    variance_max = 0.001                # [m^2] refuse take-off while the estimate is less sure
    link_min = 0.9                      # fraction of link pings answered
    settle_timeout = 10.0               # [s] to wait for the estimator to converge

    [mocap]                             # needed if any vehicle's position source is "mocap"
    backend = "vicon"                   # a motioncapture backend
    hostname = "192.168.1.10"

    [[vehicles]]
    name = "cf1"                        # the motion-capture rigid body's name
    uri = "radio://0/80/2M/E7E7E7E701"  # the radio: dongle, channel, data rate, address
    type = "cf21_mocap"
    p0 = [0.0, 0.0, 0.0]                # [m] where it is put down

Every problem is reported at once, each naming its field and the fix, as a mission's are
(:class:`FleetError`, exit 2 from the command line).
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Literal

import msgspec

from tether.checks import _uri_problem
from tether.schema import Problems, SchemaError, Strict, read_issue

SCHEMA_VERSION = 1
BACKENDS = ("vicon", "optitrack", "optitrack_closed_source", "qualisys", "vrpn", "motionanalysis", "nokov",
            "fzmotion", "mock")
"""Backend names ``motioncapture.connect`` accepts (libmotioncapture 1.x)."""
MAX_FILE_BYTES = 1 << 20
PLACE_TOLERANCE = 0.3
"""Largest distance [m] between a vehicle's place in the fleet and its agent's ``p0`` in a mission, and
between that place and the vehicle's own estimate at take-off (``plant/preflight.py``)."""

PARAM_RANGES: dict[str, tuple[float, float]] = {
    "stabilizer.estimator": (0, 3),
    "stabilizer.controller": (0, 4),
    "locSrv.extPosStdDev": (1e-4, 1.0),
    "kalman.initialX": (-100.0, 100.0),
    "kalman.initialY": (-100.0, 100.0),
    "kalman.initialZ": (-100.0, 100.0),
    "hlCommander.vtoff": (0.05, 2.0),
    "hlCommander.vland": (0.05, 2.0),
    "commander.enHighLevel": (0, 1),
}
"""Firmware parameters a fleet may set, each with the values the firmware accepts (estimator 0 any,
1 complementary, 2 Kalman, 3 UKF; controller 0 any, 1 PID, 2 Mellinger, 3 INDI, 4 Brescianini).
Others are refused: a misspelt name would otherwise be set on no vehicle, silently."""


class FleetError(SchemaError):
    """A fleet file is not valid; ``problems`` as :class:`tether.mission.MissionError`'s."""


class VehicleType(Strict, frozen=True):
    mass: float = 0.029
    """Vehicle mass [kg] with battery and markers (a Crazyflie 2.1 with its battery: 0.029)."""
    position_source: Literal["onboard", "mocap"] = "onboard"
    """``onboard``: the vehicle's own positioning (Lighthouse, Loco, flow deck) feeds its estimator;
    ``mocap``: the fleet's motion-capture system does, as external position."""
    params: dict[str, float] = {}
    """Firmware parameters set on connection, before take-off (``PARAM_RANGES`` lists those allowed)."""


class Health(Strict, frozen=True):
    battery_min: float = 3.7
    """Battery voltage [V] below which take-off is refused (1-cell LiPo, motors off)."""
    variance_max: float = 0.001
    """Largest position variance [m^2] (``kalman.varPX/PY/PZ``) take-off accepts."""
    link_min: float = 0.9
    """Smallest fraction of link pings answered that take-off accepts."""
    settle_timeout: float = 10.0
    """How long [s] to wait for the estimator to converge before refusing."""


class Mocap(Strict, frozen=True):
    backend: str
    """A ``motioncapture`` backend: vicon, optitrack, qualisys, vrpn, motionanalysis, mock, ..."""
    hostname: str = ""
    options: dict[str, str] = {}
    """Further backend options, passed on as given (the ``mock`` backend's ``rigid_bodies``)."""


class Vehicle(Strict, frozen=True):
    name: str
    """The vehicle's name, and its rigid body's name in the motion-capture system."""
    uri: str
    type: str
    p0: list[float]
    """Where the vehicle stands before take-off [m; world frame]."""
    mass: float | None = None
    """[kg]; none: its type's."""


class Fleet(Strict, frozen=True):
    version: int
    vehicles: list[Vehicle]
    types: dict[str, VehicleType] = {}
    health: Health = msgspec.field(default_factory=lambda: Health())
    mocap: Mocap | None = None

    def by_uri(self, uri: str) -> Vehicle | None:
        return next((v for v in self.vehicles if v.uri == uri), None)

    def type_of(self, v: Vehicle) -> VehicleType:
        return self.types[v.type]

    def mass_of(self, v: Vehicle) -> float:
        """The vehicle's mass [kg]: its own, else its type's."""
        return v.mass if v.mass is not None else self.types[v.type].mass


def _finite_in(x: float, lo: float, hi: float) -> bool:
    return math.isfinite(x) and lo <= x <= hi


def validate(f: Fleet) -> Problems:
    """Every problem of a decoded fleet, ``(field, "<what>; <fix>")``. Pure."""
    out: Problems = []
    if f.version != SCHEMA_VERSION:
        out.append(("version", f"is {f.version} but this release reads version {SCHEMA_VERSION}; set "
                               f"`version = {SCHEMA_VERSION}`"))
    if not f.vehicles:
        out.append(("vehicles", "is empty; add one [[vehicles]] table per Crazyflie"))
    for tname, t in f.types.items():
        where = f"types.{tname}"
        if not _finite_in(t.mass, 0.015, 0.5):
            out.append((f"{where}.mass", f"is {t.mass!r}; give the mass in kg with battery, e.g. 0.029"))
        for p, value in t.params.items():
            rng = PARAM_RANGES.get(p)
            if rng is None:
                out.append((f"{where}.params.{p}", "is not a parameter a fleet may set; use one of "
                                                   + ", ".join(sorted(PARAM_RANGES))))
            elif not _finite_in(value, *rng):
                out.append((f"{where}.params.{p}", f"is {value!r}; give a value in [{rng[0]:g}, {rng[1]:g}]"))
    h = f.health
    for name, value, lo, hi, fix in (("battery_min", h.battery_min, 3.0, 4.2, "e.g. 3.8 V"),
                                     ("variance_max", h.variance_max, 1e-6, 1.0, "e.g. 0.001 m^2"),
                                     ("link_min", h.link_min, 0.0, 1.0, "a fraction, e.g. 0.9"),
                                     ("settle_timeout", h.settle_timeout, 0.5, 120.0, "e.g. 10 s")):
        if not _finite_in(value, lo, hi):
            out.append((f"health.{name}", f"is {value!r}; give a value in [{lo:g}, {hi:g}], {fix}"))
    names: set[str] = set()
    uris: dict[str, str] = {}
    for k, v in enumerate(f.vehicles):
        where = f"vehicle {v.name}" if v.name else f"vehicles[{k}]"
        if not v.name or not v.name.replace("_", "").replace("-", "").isalnum():
            out.append((f"{where}.name", f"is {v.name!r}; give letters, digits, - or _ (the rigid body's name)"))
        if v.name in names:
            out.append((f"{where}.name", "is given to two vehicles; name each vehicle once"))
        names.add(v.name)
        problem = _uri_problem(v.uri) if "://" in v.uri else "is not a cflib URI; write e.g. radio://0/80/2M/E7E7E7E701"
        if problem is not None:
            out.append((f"{where}.uri", problem))
        elif v.uri in uris:
            out.append((f"{where}.uri", f"is also vehicle {uris[v.uri]}'s; give each vehicle its own address"))
        uris.setdefault(v.uri, v.name)
        if v.type not in f.types:
            known = ", ".join(sorted(f.types)) or "none yet"
            out.append((f"{where}.type", f"is {v.type!r}, which [types] does not define ({known}); add "
                                         f"[types.{v.type}] or use a defined type"))
        elif f.types[v.type].position_source == "mocap" and f.mocap is None:
            out.append((f"{where}.type", f"flies on motion capture ({v.type}.position_source = \"mocap\") but the "
                                         "fleet has no [mocap] table; add one with backend and hostname"))
        if len(v.p0) != 3 or not all(math.isfinite(c) for c in v.p0):
            out.append((f"{where}.p0", f"is {v.p0!r}; give [x, y, z] in metres, e.g. [0.0, 0.0, 0.0]"))
        if v.mass is not None and not _finite_in(v.mass, 0.015, 0.5):
            out.append((f"{where}.mass", f"is {v.mass!r}; give the mass in kg with battery, e.g. 0.032"))
    if f.mocap is not None:
        if f.mocap.backend not in BACKENDS:
            out.append(("mocap.backend", f"is {f.mocap.backend!r}; use one of {', '.join(BACKENDS)}"))
    return out


def loads(text: str, source: str = "<fleet>") -> Fleet:
    """Decode and validate a fleet from TOML text. Raises :class:`FleetError`."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise FleetError(source, [("<file>", f"is not valid TOML: {exc}; fix the syntax there")]) from None
    try:
        fleet = msgspec.convert(raw, type=Fleet)
    except msgspec.ValidationError as exc:
        issue = read_issue(exc)
        raise FleetError(source, [(issue.field or "<file>", f"{issue.sentence}; see the fleet file's fields in "
                                                            "docs/lab.md")]) from None
    problems = validate(fleet)
    if problems:
        raise FleetError(source, problems)
    return fleet


def load(path: str | Path) -> Fleet:
    """Read, decode and validate a fleet file. Raises :class:`FleetError` (also for a missing file)."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise FleetError(str(path), [("<file>", f"cannot be read ({exc.strerror or exc}); check the mission's "
                                                "`fleet` path (relative to the mission file)")]) from None
    if len(data) > MAX_FILE_BYTES:
        raise FleetError(str(path), [("<file>", "is larger than 1 MiB; a fleet file lists vehicles, keep it small")])
    try:
        text = data.decode()
    except UnicodeDecodeError:
        raise FleetError(str(path), [("<file>", "is not UTF-8 text; save it as UTF-8")]) from None
    return loads(text, source=str(path))
