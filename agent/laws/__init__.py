"""Formation laws: the contract every engine runs a law through, and the laws shipped with tether.

A formation law is a class with

* ``name``: what the run file and ``tether top`` call it;
* ``state``: the names of its per-axis state (Eq. 17's ``("kp", "kv")``; ``()`` for a law without
  memory). Each name is one float per axis per agent, and is what the run file, the MCAP export,
  ``tether top`` and the figures call that variable (a Python identifier, distinct);
* ``units`` (optional): the unit of each state variable, in the order of ``state`` (e.g.
  ``("1/s^2", "1/s")``); ``()`` when the law does not say;
* ``Params``: a :class:`msgspec.Struct` of its parameters, read from the mission's ``[law.params]``
  (a built-in law reads the ``[law]`` fields it always had); :meth:`FormationLaw.check` adds what a
  type cannot say, as ``(field, message)`` pairs that name the field and the fix;
* :meth:`FormationLaw.initial`: the state at t = 0, ``len(state)`` tuples of ``d`` floats;
* :meth:`FormationLaw.coefficients`: per axis, a tuple of floats computed once from the
  parameters and the control period ``h`` [s] (exponentials, products of rates and ``h``: what the
  step should not recompute every tick);
* ``step``: the law itself, a static method on one axis of one agent::

      step(ka, p, v, sp, sv, sa, sd, x, c) -> (u, xi, zeta, x_next)

  ``ka = kappa_i = sum_j a_ij``; ``p, v`` the agent's own position [m] and velocity [m/s] on this
  axis; ``sp, sv, sa`` the weighted sums ``sum_j a_ij p_j``, ``sum_j a_ij v_j``, ``sum_j a_ij a_j``
  over its in-neighbours (the leader among them where it hears it; ``sa`` is 0 with
  ``feedforward = "none"``); ``sd = sum_j a_ij delta_ij`` [m], the constant formation offset term;
  ``x`` the tuple of its state, ``c`` its coefficients (a tuple, or in the compiled engines a row
  of an array: the step only indexes it, ``c[0]``). It returns the command ``u``
  [m/s^2], the errors ``xi`` and ``zeta`` recorded beside it (Eq. 8, 9, or what the law calls its
  errors), and the state for the next tick (``len(state)`` floats).
* ``rate`` (optional; the reference simulator's ``continuous`` mode needs it): the law in
  continuous time, ``rate(ka, p, v, sp, sv, sd, b, x, r) -> (row, xi, zeta, x_dot)``, where ``b``
  is ``a_i0 a_ref + kappa_i d_i`` and ``row`` is ``b`` plus ``kappa_i u_i - sum_wa``: agent i's
  row of the algebraic loop ``L1 vdot = row`` (the neighbours' exact accelerations fed forward);
  :meth:`FormationLaw.rates` gives ``r``.

The step is written once, with ``+ - * /`` and calls of other such functions only (no branch on
a value, no numpy, no ``math``): the agent process runs it on Python floats, the reference
simulator's numpy path on arrays of every agent at once (broadcasting), and the compiled engines
compile it with numba into their loops (:mod:`sim.lawkernels`). Each runs the same IEEE operations
in the same order, so a law's runs are equal bit for bit across the engines.

What the contract excludes: the neighbour sums are weighted sums in row order, taken by the
engine (a law cannot see its neighbours one by one, nor their ids); the safety supervisor, the
saturation, collision avoidance and the link policy wrap every law alike. The run file, the
telemetry and what is shown of a run carry every state variable by its name
(``Run.law_state``, ``Telemetry.x``); the supervisor's gain bound and the ``kp``/``kv`` columns
kept for the callers that read them are the first two state variables (zeros where a law has
fewer).

A mission names a law by ``[law] kind`` (``"sigma"``, ``"benchmark"``: :data:`BUILTIN`) or by
``[law] use = "package.module:Class"`` (:func:`resolve`).
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import msgspec

from tether import wire

Problems = list[tuple[str, str]]
"""``(field, message)`` pairs, as :func:`tether.checks.validate` gives them."""

MAX_STATE = wire.MAX_STATE
"""The most per-axis state variables a law may have (the compiled engines' loaders, the telemetry)."""

MAX_COEFFICIENTS = 8
"""The most per-axis coefficients a law may have."""


class FormationLaw:
    """The contract of a formation law (see the module's documentation); subclass it."""

    name: ClassVar[str]
    state: ClassVar[tuple[str, ...]] = ()
    units: ClassVar[tuple[str, ...]] = ()
    Params: ClassVar[type[msgspec.Struct]]
    step: ClassVar[Callable[..., tuple[Any, Any, Any, tuple[Any, ...]]]]

    def check(self, params: Any, dim: int) -> Problems:
        """What the parameters' types cannot say, as ``(field, message)`` pairs (fields relative to
        the law's table, e.g. ``"kp"`` or ``"kp[1]"``); empty when they are usable."""
        return []

    def initial(self, params: Any, dim: int) -> tuple[tuple[float, ...], ...]:
        """The state at t = 0: per state variable, ``dim`` floats."""
        return ()

    def coefficients(self, params: Any, h: float, dim: int) -> tuple[tuple[float, ...], ...]:
        """Per axis, the coefficients ``c`` of :meth:`step` for the control period ``h`` [s]."""
        return ((),) * dim

    def rates(self, params: Any, dim: int) -> tuple[tuple[float, ...], ...]:
        """Per axis, the coefficients ``r`` of ``rate`` (a law with a continuous-time form)."""
        return ((),) * dim


def per_axis(value: float | Sequence[float], dim: int) -> tuple[float, ...]:
    """One float for every axis, or the ``dim`` floats of a list, as a tuple of floats."""
    if isinstance(value, (int, float)):
        return (float(value),) * dim
    return tuple(float(x) for x in value)


def axis_problems(value: float | Sequence[float], dim: int, field: str) -> Problems:
    """A per-axis list that does not have ``dim`` values, as a problem naming ``field``."""
    if not isinstance(value, (int, float)) and len(value) != dim:
        return [(field, f"has {len(value)} component(s) but the mission has dim = {dim}; give one number for "
                        f"every axis or {dim} components")]
    return []


BUILTIN: dict[str, str] = {
    "sigma": "agent.laws.sigma:Sigma",
    "benchmark": "agent.laws.benchmark:Benchmark",
    "integral": "agent.laws.integral:Integral",
}
"""The laws shipped with tether, by the name a mission's ``[law] kind`` gives them."""


class LawNotFound(ValueError):
    """A ``[law] use`` that names no law: the message says which part and how to fix it."""


def resolve(use: str) -> FormationLaw:
    """The law a mission names: a built-in's name (:data:`BUILTIN`) or ``"package.module:Class"``
    (importable from the current directory or ``sys.path``). Raises :class:`LawNotFound`."""
    target = BUILTIN.get(use, use)
    module_name, sep, attr = target.partition(":")
    if not sep or not module_name or not attr:
        raise LawNotFound(f"is {use!r}; name a law shipped with tether ({', '.join(BUILTIN)}) or a class as "
                          "\"package.module:Class\"")
    try:
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError:
            # a console script's sys.path lacks the working directory that `python -m` puts first: a
            # law module beside the mission, run from its directory, imports as it would there
            if os.getcwd() in sys.path:
                raise
            sys.path.append(os.getcwd())
            module = importlib.import_module(module_name)
    except ImportError as exc:
        raise LawNotFound(f"is {use!r} but module {module_name!r} does not import ({exc}); put it on the Python "
                          "path (run from the directory that holds it, or set PYTHONPATH)") from exc
    cls = getattr(module, attr, None)
    if not (isinstance(cls, type) and issubclass(cls, FormationLaw)):
        raise LawNotFound(f"is {use!r} but {module_name} has no FormationLaw subclass {attr!r}; name a class "
                          "deriving from agent.laws.FormationLaw")
    law = cls()
    if len(law.state) > MAX_STATE:
        raise LawNotFound(f"is {use!r}, a law of {len(law.state)} state variables per axis; the engines take at "
                          f"most {MAX_STATE}")
    why = state_problem(law)
    if why:
        raise LawNotFound(f"is {use!r}, whose {why}")
    return law


def state_problem(law: FormationLaw) -> str:
    """What is wrong with ``law``'s ``state`` and ``units`` declaration ('' when nothing): names
    that are not distinct Python identifiers (they name arrays and columns), or a ``units`` that is
    neither empty nor one unit per state variable."""
    names, units = law.state, law.units
    bad = [x for x in names if not (isinstance(x, str) and x.isidentifier() and len(x) <= wire.MAX_NAME)]
    if bad:
        return (f"state names {bad!r} are not Python identifiers of at most {wire.MAX_NAME} characters; name each "
                "state variable like a variable")
    if len(set(names)) != len(names):
        return f"state names {names!r} repeat a name; give each state variable its own name"
    if units and (len(units) != len(names) or not all(isinstance(x, str) for x in units)):
        return (f"units {units!r} do not match its state {names!r}; give one unit (a string) per state variable, "
                "or none")
    return ""


class Bound(msgspec.Struct, frozen=True):
    """A mission's law with its decoded parameters, for ``dim`` axes."""

    law: FormationLaw
    params: Any
    dim: int

    @property
    def name(self) -> str:
        return self.law.name

    def initial(self) -> tuple[tuple[float, ...], ...]:
        """Per state variable, ``dim`` floats: the state at t = 0."""
        return tuple(tuple(float(x) for x in row) for row in self.law.initial(self.params, self.dim))

    def coefficients(self, h: float) -> tuple[tuple[float, ...], ...]:
        """Per axis, the step's coefficients for the control period ``h`` [s]."""
        return tuple(tuple(float(x) for x in row) for row in self.law.coefficients(self.params, h, self.dim))

    def rates(self) -> tuple[tuple[float, ...], ...]:
        """Per axis, the continuous-time form's coefficients."""
        return tuple(tuple(float(x) for x in row) for row in self.law.rates(self.params, self.dim))

    @property
    def units(self) -> tuple[str, ...]:
        """The unit of each state variable ('' where the law does not say)."""
        return tuple(self.law.units) or ("",) * len(self.law.state)

    def shown(self, state: Any, zero: Any) -> tuple[Any, Any]:
        """The two state columns the supervisor's gain bound reads (and ``Run.kp``/``Run.kv``,
        ``Telemetry.kp``/``kv``): the first two state variables, ``zero`` where the law has fewer."""
        return (state[0] if len(state) > 0 else zero), (state[1] if len(state) > 1 else zero)


def _decode(law: FormationLaw, raw: dict[str, Any], where: str) -> tuple[Any, Problems]:
    try:
        return msgspec.convert(raw, law.Params), []
    except msgspec.ValidationError as exc:
        text = str(exc)
        field = where
        if " - at `$." in text:
            text, _, path = text.partition(" - at `$.")
            field = f"{where}.{path.rstrip('`')}"
        elif "missing required field" in text:
            name = text.rpartition("`")[0].rpartition("`")[2]
            field, text = f"{where}.{name}", f"is missing; {law.name} needs it ({text})"
        elif "unknown field" in text:
            name = text.rpartition("`")[0].rpartition("`")[2]
            fields = ", ".join(f.name for f in msgspec.structs.fields(law.Params))
            field, text = f"{where}.{name}", f"is not a parameter of {law.name}; it takes {fields}"
        return None, [(field, text)]


def bind(m: Any) -> tuple[Bound | None, Problems]:
    """The law of mission ``m`` (a :class:`tether.mission.Mission`) with its parameters, or the
    problems that stop it (fields named from the mission's top: ``law.use``, ``law.params.kp``)."""
    cfg = m.law
    if cfg.kind == "custom":
        if not cfg.use:
            return None, [("law", "names no law; set kind = \"sigma\" or \"benchmark\", or use = "
                                  "\"package.module:Class\" for a law of your own")]
        try:
            law = resolve(cfg.use)
        except LawNotFound as exc:
            return None, [("law.use", str(exc))]
        params, out = _decode(law, dict(cfg.params), "law.params")
        where = "law.params"
    else:
        law = resolve(cfg.kind)
        out = []
        if cfg.use or cfg.params:
            out.append(("law.use" if cfg.use else "law.params",
                        f"is set but kind = {cfg.kind!r} is a law shipped with tether; remove it, or remove kind to "
                        "run the law it names"))
        if cfg.kind == "sigma" and cfg.sigma is None:
            out.append(("law.sigma", "is missing but the sigma law (Eq. 17) needs it; add e.g. `sigma = 1.0`, "
                                     "or use kind = \"benchmark\""))
        elif cfg.kind == "sigma" and cfg.sigma <= 0:
            out.append(("law.sigma", f"is {cfg.sigma} but Theorem 1 needs sigma > 0; set e.g. `sigma = 1.0`, "
                                     "or use kind = \"benchmark\" for a law without leakage"))
        raw = {"kp0": cfg.kp0, "kv0": cfg.kv0, "gamma_p": cfg.gamma_p, "gamma_v": cfg.gamma_v}
        if cfg.sigma is not None:
            raw["sigma"] = cfg.sigma
        params, more = _decode(law, raw, "law")
        out += more
        where = "law"
    if params is None:
        return None, out
    out += [(f"{where}.{field}", text) for field, text in law.check(params, m.dim)
            if not any(f == f"{where}.{field}" for f, _ in out)]
    return (Bound(law, params, m.dim) if not out else None), out


def of_mission(m: Any) -> Bound:
    """:func:`bind`'s law, or ValueError naming the first problem's field."""
    bound, out = bind(m)
    if bound is None:
        field, text = out[0]
        raise ValueError(f"{field} {text}")
    return bound
