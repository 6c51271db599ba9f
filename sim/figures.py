"""Figures for papers: Fig. 4-style comparisons and per-run panels.

Uses matplotlib's non-interactive Agg backend; every function takes runs and a path and returns
the PNG paths it wrote, each with an SVG of the same figure beside it (vector, for a paper). Long
runs are drawn as envelopes (min/max per bin), with their first and last seconds zoomed; safety
events are numbered on the time axis (labels that never overprint) and listed under the errors.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from sim import metrics  # noqa: E402
from tether.runfile import Run  # noqa: E402

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

AXES = "xyz"


LINESTYLES = ("-", "--", ":")
"""Per axis (x, y, z) in the gain panels; the colour is the agent's."""
GAIN_UNITS = ("[1/s²]", "[1/s]")
"""Units of Kp and Kv (Eq. 17 with dimensionless weights; ``docs/mission.md``)."""
ENVELOPE = 2000
"""Above this many samples a series is drawn as its envelope: min and max over this many bins."""
ZOOM = 5.0
"""Seconds of a long run's start and end drawn at full resolution beside its whole length."""
LONG = 60.0
"""A run longer than this [s] gets the zoomed columns."""
ASPECT_LIMIT = 4.0
"""A world view is drawn to scale (equal aspect) unless its extents differ by more than this factor."""
COINCIDE = 5e-3
"""Curves closer than this fraction of their panel's range everywhere are noted as coinciding."""


def colour(i: int) -> str:
    """The colour of the run's i-th agent (by column), the same in every panel of every figure."""
    return f"C{i % 10}"


def title(run: Run, what: str = "") -> str:
    """A figure's title: the mission and the law it flew (every figure names its law)."""
    head = f"{run.meta.mission}, law {run.meta.law}"
    return f"{head}: {what}" if what else head


def series(ax: Axes, t: np.ndarray, y: np.ndarray, color: str, label: str | None, ls: str = "-",
           lw: float = 0.8) -> None:
    """``y`` over ``t`` as a line, or (more than :data:`ENVELOPE` samples) as its envelope: the band
    between the min and max of each bin, outlined in the same colour, so that no curve's band hides
    another's."""
    if len(t) <= ENVELOPE:
        ax.plot(t, y, lw=lw, color=color, ls=ls, label=label)
        return
    starts = np.linspace(0, len(t), ENVELOPE + 1).astype(int)[:-1]
    with np.errstate(invalid="ignore"):
        lo = np.fmin.reduceat(y, starts)
        hi = np.fmax.reduceat(y, starts)
    tc = t[starts]
    ax.fill_between(tc, lo, hi, color=color, alpha=0.18, lw=0)
    ax.plot(tc, hi, lw=0.5, color=color, ls=ls, label=label)
    ax.plot(tc, lo, lw=0.5, color=color, ls=ls)


def _decimate(run: Run, max_points: int = 4000) -> slice:
    return slice(None, None, max(1, len(run.t) // max_points))


def mission_offsets(run: Run) -> np.ndarray | None:
    """The formation offsets ``h_i`` (N, d) of the run's agents, from its mission text; None
    when the run holds none (or one this version cannot read)."""
    from tether import mission as ms

    if not run.meta.mission_text:
        return None
    try:
        m = ms.loads(run.meta.mission_text)
    except Exception:  # noqa: BLE001 - an old or foreign mission text: figures without slots
        return None
    by_id = {a.id: a.offset for a in m.agents}
    if not all(int(aid) in by_id for aid in run.agent_ids):
        return None
    return np.array([by_id[int(aid)] for aid in run.agent_ids], dtype=float)


def coinciding(curves: list[tuple[str, np.ndarray]], rel: float = COINCIDE) -> list[list[str]]:
    """Groups (two or more labels) of curves that coincide: every pair in a group is within
    ``rel`` of the panel's range of each other at every sample (NaN where both are NaN)."""
    finite = [y[np.isfinite(y)] for _, y in curves]
    values = np.concatenate(finite) if finite else np.array([])
    if values.size == 0:
        return []
    span = float(np.ptp(values)) or max(1.0, float(np.max(np.abs(values))))
    tol = rel * span
    groups: list[list[int]] = []
    for n, (_, y) in enumerate(curves):
        for g in groups:
            ref = curves[g[0]][1]
            both_nan = np.isnan(y) & np.isnan(ref)
            if y.shape == ref.shape and np.all(both_nan | (np.abs(y - ref) <= tol)):
                g.append(n)
                break
        else:
            groups.append([n])
    return [[curves[n][0] for n in g] for g in groups if len(g) > 1]


def note_coinciding(ax: Axes, curves: list[tuple[str, np.ndarray]]) -> list[list[str]]:
    """Write in ``ax`` which of its curves coincide (so that a hidden curve is not taken for a
    missing one); returns the groups."""
    groups = coinciding(curves)
    if groups:
        text = "coincide: " + "; ".join(" = ".join(g) for g in groups)
        ax.text(0.99, 0.03, text, transform=ax.transAxes, ha="right", va="bottom", fontsize=6, wrap=True,
                bbox={"boxstyle": "round", "fc": "white", "ec": "0.7", "alpha": 0.85})
    return groups


def further_state(runs: Iterable[Run]) -> dict[str, str]:
    """The law state variables of ``runs`` beyond the two gain rows (the third and later of each
    law's ``state``), by name in order of first appearance, each with its axis label: its name and
    the unit the law declares (``"s [m s]"``)."""
    out: dict[str, str] = {}
    for run in runs:
        units = run.meta.law_units or ("",) * len(run.meta.law_state)
        for name, unit in list(zip(run.meta.law_state, units))[2:]:
            out.setdefault(name, f"{name} [{unit}]" if unit else name)
    return out


def comparison_figure(runs: dict[str, Run], title: str = "") -> Figure:
    """Fig. 4 layout (:func:`comparison`), unsaved."""
    cols = len(runs)
    more = further_state(runs.values())
    rows = 3 + len(more)
    fig, ax = plt.subplots(rows, cols, figsize=(5.2 * cols, 8.0 * rows / 3), sharex="col", squeeze=False)
    for c, (label, run) in enumerate(runs.items()):
        t = run.t
        xn = metrics.xi_norm(run)
        curves: list[list[tuple[str, np.ndarray]]] = [[] for _ in range(rows)]
        for i, aid in enumerate(run.agent_ids):
            series(ax[0, c], t, xn[:, i], colour(i), f"agent {aid}")
            curves[0].append((f"{aid}", xn[:, i]))
            for k in range(run.kp.shape[2]):
                ls = LINESTYLES[k % 3]
                series(ax[1, c], t, run.kp[:, i, k], colour(i), f"{aid}{AXES[k]}", ls)
                series(ax[2, c], t, run.kv[:, i, k], colour(i), f"{aid}{AXES[k]}", ls)
                curves[1].append((f"{aid}{AXES[k]}", run.kp[:, i, k]))
                curves[2].append((f"{aid}{AXES[k]}", run.kv[:, i, k]))
        for row, (name, axis_label) in enumerate(more.items(), start=3):  # one panel per further variable
            ax[row, c].set_ylabel(axis_label)
            if name not in run.meta.law_state:
                continue
            x = run.state(name)
            for i, aid in enumerate(run.agent_ids):
                for k in range(x.shape[2]):
                    series(ax[row, c], t, x[:, i, k], colour(i), f"{aid}{AXES[k]}", LINESTYLES[k % 3])
                    curves[row].append((f"{aid}{AXES[k]}", x[:, i, k]))
        ax[0, c].set_title(f"law {label}" if label == run.meta.law else f"{label} (law {run.meta.law})")
        mark_events(run, ax[:, c])
        ax[0, c].set_ylabel(r"agents' own $\|\xi_i\|$ [m]")
        ax[1, c].set_ylabel(r"$K_p$ " + GAIN_UNITS[0])
        ax[2, c].set_ylabel(r"$K_v$ " + GAIN_UNITS[1])
        ax[rows - 1, c].set_xlabel("t [s]")
        for r in range(rows):
            ax[r, c].grid(True, lw=0.3)
            note_coinciding(ax[r, c], curves[r])
        ax[0, c].legend(fontsize=7, loc="upper right")
        ax[1, c].legend(fontsize=6, ncol=2, loc="upper left")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def _save(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` to ``path`` (PNG) and, beside it, the same figure as SVG; close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150)
    fig.savefig(path.with_suffix(".svg"))
    plt.close(fig)
    return path


def comparison(runs: dict[str, Run], path: str | Path, title: str = "") -> Path:
    """Fig. 4 layout: one column per run (e.g. sigma-modification, benchmark), rows ||xi_i||, Kp, Kv,
    then one row per further state variable of the laws (the integral law's ``s``), labelled with
    its name and unit (:func:`further_state`); one colour per agent (:func:`colour`), one line
    style per axis in the state rows, and a note where curves coincide."""
    return _save(comparison_figure(runs, title), path)


def event_lines(run: Run) -> list[str]:
    """The run's safety events, numbered as :func:`mark_events` numbers them: ``"3  t = 12.40 s
    vehicle 2: FLYING -> HOLD (leader silent 0.52 s)"``."""
    modes = run.meta.modes

    def name(code: int) -> str:
        return modes[code] if 0 <= code < len(modes) else str(code)

    return [f"{n}  t = {e.t:.2f} s  vehicle {e.vehicle}: {name(e.src)} -> {name(e.dst)}" + (
        f" ({e.reason})" if e.reason else "") for n, e in enumerate(sorted(run.safety.events, key=lambda e: e.t), 1)]


LABEL_GAP = 0.04
"""Events closer than this fraction of the time axis share one label (``4-7``)."""


def event_labels(times: list[float], span: float) -> list[tuple[float, str, int]]:
    """Labels of events at ``times`` (sorted) on an axis ``span`` s long: ``(t, text, level)``, one per
    cluster of events within :data:`LABEL_GAP` of the span of each other (numbered from 1, ``4-7``
    for several), on alternating levels, so that no two labels overprint."""
    gap = LABEL_GAP * max(span, 1e-9)
    clusters: list[list[int]] = []
    for n, t in enumerate(times):
        if clusters and t - times[clusters[-1][0]] <= gap:
            clusters[-1].append(n)
        else:
            clusters.append([n])
    return [(times[c[0]], f"{c[0] + 1}" if len(c) == 1 else f"{c[0] + 1}-{c[-1] + 1}", level % 2)
            for level, c in enumerate(clusters)]


def mark_events(run: Run, axes: Iterable[Axes], numbers: bool = True) -> None:
    """A vertical line on each of ``axes`` (time-series panels) per safety event of ``run``, numbered
    on the first as :func:`event_lines` lists them (:func:`event_labels`: labels never overprint);
    nothing when the run has none."""
    axes = list(axes)
    events = sorted(run.safety.events, key=lambda e: e.t)
    for e in events:
        for a in axes:
            a.axvline(e.t, color="tab:red", ls="-.", lw=0.7, alpha=0.7)
    if not numbers or not events:
        return
    lo, hi = axes[0].get_xlim()
    for t, text, level in event_labels([e.t for e in events], hi - lo):
        axes[0].annotate(text, (t, 1.0), xycoords=("data", "axes fraction"), xytext=(0, 2 + 9 * level),
                         textcoords="offset points", fontsize=6, color="tab:red", ha="center", va="bottom",
                         annotation_clip=False)


def error_rows(run: Run, geometry: metrics.Geometry | None) -> list[tuple[str, list[tuple[str, np.ndarray]]]]:
    """The rows of :func:`errors_figure`: ``(y label, [(curve label, (T,) values)])``; the true
    formation error and the tracking error only where the run holds its mission."""
    ids = [int(a) for a in run.agent_ids]
    rows = []
    if geometry is not None:
        true, track = metrics.true_xi_norm(run, geometry), metrics.tracking_norm(run, geometry)
        rows += [("true formation error\n" + r"$\|\xi_i\|$ (Eq. 8, positions) [m]",
                  [(f"agent {a}", true[:, i]) for i, a in enumerate(ids)]),
                 ("tracking error\n" + r"$\|p_i - h_i - p_L\|$ [m]",
                  [(f"agent {a}", track[:, i]) for i, a in enumerate(ids)])]
    own = metrics.xi_norm(run)
    rows.append(("agents' own " + r"$\|\xi_i\|$" + "\n(from the data they had) [m]",
                 [(f"agent {a}", own[:, i]) for i, a in enumerate(ids)]))
    for name, k, unit in (("K_p", run.kp, GAIN_UNITS[0]), ("K_v", run.kv, GAIN_UNITS[1])):
        rows.append((f"${name}$ {unit}", [(f"{a}{AXES[x]}", k[:, i, x]) for i, a in enumerate(ids)
                                          for x in range(k.shape[2])]))
    return rows


def lost_positions(run: Run) -> list[tuple[int, float]]:
    """``(vehicle, t)``: the vehicles whose recorded position ends before the run does (a process
    killed or cut off), with the time of their last position, among the ticks the run recorded."""
    rows = np.flatnonzero(np.isfinite(run.t))
    if not rows.size:
        return []
    last_tick = int(rows[-1])
    out = []
    for i, aid in enumerate(run.agent_ids):
        have = np.flatnonzero(np.all(np.isfinite(run.p[:, i]), axis=1))
        if have.size and int(have[-1]) < last_tick:
            out.append((int(aid), float(run.t[have[-1]])))
    return out


def errors_figure(run: Run, geometry: metrics.Geometry | None = None) -> Figure:
    """Errors and gains over time (``errors_gains.png``), unsaved: the true formation error and the
    tracking error (when the run holds its mission), the agents' own ``||xi_i||``, ``Kp`` and ``Kv``
    in their units; a run longer than :data:`LONG` s as envelopes with its first and last
    :data:`ZOOM` s beside; the safety events numbered and listed underneath."""
    if geometry is None:
        geometry = metrics.geometry(run)
    rows = error_rows(run, geometry)
    t = run.t
    finite = t[np.isfinite(t)]
    long = finite.size > 1 and finite[-1] - finite[0] > LONG
    events = event_lines(run)
    widths = [1.0, 3.0, 1.0] if long else [1.0]
    heights = [1.0] * len(rows) + ([0.12 * min(len(events), 12) + 0.1] if events else [])
    fig, ax = plt.subplots(len(heights), len(widths), figsize=(12.0 if long else 8.0, 2.0 * len(rows) + 1.0
                                                                  + (0.25 * min(len(events), 12) if events else 0)),
                           squeeze=False, gridspec_kw={"width_ratios": widths, "height_ratios": heights})
    whole = 1 if long else 0
    windows = [(finite[0], finite[0] + ZOOM), None, (finite[-1] - ZOOM, finite[-1])] if long else [None]
    for r, (ylabel, curves) in enumerate(rows):
        for c, window in enumerate(windows):
            a = ax[r, c]
            if window is None:
                sel = slice(None)
            else:
                k = np.flatnonzero((t >= window[0]) & (t <= window[1]))
                sel = slice(int(k[0]), int(k[-1]) + 1) if k.size else slice(0, 0)
            for n, (label, y) in enumerate(curves):
                i = n // run.kp.shape[2] if label[-1] in AXES else n
                ls = LINESTYLES[n % run.kp.shape[2]] if label[-1] in AXES else "-"
                series(a, t[sel], y[sel], colour(i), label if c == whole else None, ls)
            a.grid(True, lw=0.3)
            if window is not None:
                a.set_xlim(*window)
                a.tick_params(labelsize=7)
            if c == 0:
                a.set_ylabel(ylabel, fontsize=8)
        note_coinciding(ax[r, whole], curves)
    for r in range(len(rows)):  # one time axis for every panel of the whole run
        ax[r, whole].set_xlim(float(finite[0]), float(finite[-1]))
    if geometry is not None:
        lost = lost_positions(run)
        if lost:
            ax[0, whole].text(0.01, 0.97, "; ".join(f"no position of vehicle {aid} after {t:.1f} s" for aid, t in lost)
                              + ": Eq. 8 is undefined for it and the agents that hear it (tracking error below)",
                              transform=ax[0, whole].transAxes, fontsize=6, va="top", ha="left",
                              bbox={"boxstyle": "round", "fc": "white", "ec": "0.7", "alpha": 0.85})
    if long:
        ax[0, 0].set_title(f"first {ZOOM:g} s", fontsize=9)
        ax[0, 2].set_title(f"last {ZOOM:g} s", fontsize=9)
    mark_events(run, ax[: len(rows), whole])
    for c in range(len(widths)):
        ax[len(rows) - 1, c].set_xlabel("t [s]")
        if c != whole:
            mark_events(run, ax[: len(rows), c], numbers=False)
    ax[0, whole].legend(fontsize=7, loc="upper right", ncol=2)
    ax[len(rows) - 2, whole].legend(fontsize=6, ncol=4, loc="upper right")
    if events:
        for c in range(len(widths)):
            ax[-1, c].axis("off")
        shown = events[:12] + ([f"... and {len(events) - 12} more (events.json, report.html)"]
                               if len(events) > 12 else [])
        ax[-1, whole].text(0.0, 1.0, "safety events:\n" + "\n".join(shown), va="top", ha="left", fontsize=7,
                           color="tab:red", transform=ax[-1, whole].transAxes)
    fig.suptitle(title(run, "errors and gains"))
    fig.tight_layout()
    return fig


def velocities_figure(run: Run) -> Figure:
    """Each agent's velocity against the leader's, per axis (unsaved)."""
    dim = run.v.shape[2]
    fig, ax = plt.subplots(dim, 1, figsize=(7, 2.3 * dim), sharex=True, squeeze=False)
    for k in range(dim):
        curves = []
        for i, aid in enumerate(run.agent_ids):
            series(ax[k, 0], run.t, run.v[:, i, k], colour(i), f"agent {aid}")
            curves.append((f"{aid}", run.v[:, i, k]))
        series(ax[k, 0], run.t, run.leader_v[:, k], "k", "leader", "--", 1.0)
        curves.append(("leader", run.leader_v[:, k]))
        ax[k, 0].set_ylabel(f"$v_{AXES[k]}$ [m/s]")
        ax[k, 0].grid(True, lw=0.3)
        note_coinciding(ax[k, 0], curves)
    mark_events(run, ax[:, 0])
    ax[0, 0].legend(fontsize=7, ncol=3)
    ax[-1, 0].set_xlabel("t [s]")
    fig.suptitle(title(run, "velocities"), fontsize=10)
    fig.tight_layout()
    return fig


def _snapshot_ticks(run: Run, fracs: tuple[float, ...] = (0.0, 0.25, 0.5, 1.0)) -> list[int]:
    rows = np.flatnonzero(np.all(np.isfinite(run.p[:, :, :2]), axis=(1, 2)))
    if not len(rows):
        return []
    return sorted({int(rows[min(len(rows) - 1, int(f * (len(rows) - 1)))]) for f in fracs})


def _ring(xy: np.ndarray, order: np.ndarray) -> np.ndarray:
    return np.vstack([xy[order], xy[order[:1]]])


def _scale_or_note(ax: Axes, xy: np.ndarray, what: str) -> bool:
    """Equal aspect when the extents of ``xy`` allow it (:data:`ASPECT_LIMIT`), else a note in the
    title that the axes are not to scale. Returns whether it is to scale."""
    ext = np.nanmax(xy, axis=0) - np.nanmin(xy, axis=0)
    ext = np.where(np.isfinite(ext), ext, 0.0)
    small, large = float(min(ext)), float(max(ext))
    if large <= ASPECT_LIMIT * max(small, 1e-9) or large == 0.0:
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(what)
        return True
    ax.set_title(f"{what}\n(not to scale: x spans {ext[0]:.4g} m, y {ext[1]:.4g} m; "
                 "the formation is to scale on the right)", fontsize=9)
    return False


def xy_figure(run: Run, offsets: np.ndarray | None = None) -> Figure:
    """The world view (paths, formation snapshots, target slots) beside the view relative to the
    leader (drawn to scale, target slots ``h_i`` and the target polygon), unsaved."""
    if offsets is None:
        offsets = mission_offsets(run)
    sl = _decimate(run)
    n = len(run.agent_ids)
    fig, (axp, axr) = plt.subplots(1, 2, figsize=(12, 6.2))
    target = offsets[:, :2] if offsets is not None else None
    ticks = _snapshot_ticks(run)
    order_of = (lambda xy: _polygon(target)) if target is not None else _polygon  # noqa: E731
    for i, aid in enumerate(run.agent_ids):
        axp.plot(run.p[sl, i, 0], run.p[sl, i, 1], lw=0.7, color=colour(i), label=f"agent {aid}")
        rel = run.p[sl, i, :2] - run.leader_p[sl, :2]
        axr.plot(rel[:, 0], rel[:, 1], lw=0.5, alpha=0.6, color=colour(i), label=f"agent {aid}")
    axp.plot(run.leader_p[sl, 0], run.leader_p[sl, 1], "k--", lw=0.8, label="leader")
    for n_snap, k in enumerate(ticks):
        xy = run.p[k, :, :2]
        lead = run.leader_p[k, :2]
        order = order_of(xy)
        first = n_snap == 0
        if target is not None:
            slots = lead + target
            axp.plot(*_ring(slots, _polygon(target)).T, "--", lw=0.7, color="0.55",
                     label="target formation" if first else None)
            axp.scatter(slots[:, 0], slots[:, 1], s=60, facecolors="none",
                        edgecolors=[colour(i) for i in range(n)], lw=1.0, label="target slots" if first else None)
        axp.plot(*_ring(xy, order).T, "k:", lw=0.8, label="formation" if first else None)
        axp.scatter(xy[:, 0], xy[:, 1], marker="^", s=36, c=[colour(i) for i in range(n)], zorder=3)
        axp.plot(lead[0], lead[1], "*", ms=10, color="k")
        axp.annotate(f"t={run.t[k]:.0f}s", lead, fontsize=7, xytext=(4, 4), textcoords="offset points")
        rel = xy - lead
        axr.plot(*_ring(rel, order).T, ":", lw=0.8, color="0.3")
        axr.scatter(rel[:, 0], rel[:, 1], marker="^", s=36, c=[colour(i) for i in range(n)], zorder=3)
        axr.annotate(f"t={run.t[k]:.0f}s", rel[order[0]], fontsize=7, xytext=(4, 4), textcoords="offset points")
    if target is not None:
        axr.plot(*_ring(target, _polygon(target)).T, "--", lw=1.0, color="0.45", label="target formation")
        axr.scatter(target[:, 0], target[:, 1], s=140, facecolors="none", edgecolors=[colour(i) for i in range(n)],
                    lw=1.4, label="target slots $h_i$", zorder=4)
    axr.plot(0.0, 0.0, "*", ms=12, color="k", label="leader")
    _landed(run, axr)
    world = np.concatenate([run.p[:, :, :2].reshape(-1, 2), run.leader_p[:, :2]])
    _scale_or_note(axp, world, "paths and formation snapshots")
    axp.set_xlabel("x [m]")
    axp.set_ylabel("y [m]")
    axr.set_xlabel("x - x_leader [m]")
    axr.set_ylabel("y - y_leader [m]")
    axr.set_title("positions relative to the leader (to scale, vehicles in flight)")
    axr.set_aspect("equal", adjustable="datalim")
    _frame_flying(run, axr, target)
    for ax in (axp, axr):  # legends below the axes: they never hide a snapshot
        ax.grid(True, lw=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=4, frameon=False)
    fig.suptitle(title(run, "paths"), fontsize=10)
    fig.tight_layout()
    return fig


GROUNDED = ("LAND", "LANDED", "ESTOP")
"""Modes in which a vehicle no longer holds its slot: the relative view is not scaled to it."""


def flying(run: Run) -> np.ndarray:
    """``(T, N)`` bool: the vehicle's supervisor is in a mode that holds its slot (not
    :data:`GROUNDED`, and a sample recorded)."""
    grounded = [c for c, name in enumerate(run.meta.modes) if name in GROUNDED]
    mode = run.safety.safety_mode
    return (mode >= 0) & ~np.isin(mode, grounded)


def _landed(run: Run, ax: Axes) -> None:
    """Mark, relative to the leader, where each vehicle left its slot for good (its last tick in
    flight, :func:`flying`), with its id and the time."""
    fly = flying(run)
    for i, aid in enumerate(run.agent_ids):
        up = np.flatnonzero(fly[:, i])
        if up.size == 0 or up[-1] == len(run.t) - 1:
            continue
        k = int(up[-1])
        rel = run.p[k, i, :2] - run.leader_p[k, :2]
        ax.scatter([rel[0]], [rel[1]], marker="X", s=90, color=colour(i), edgecolors="k", zorder=5,
                   label="left its slot (landing, landed or stopped)" if not ax.get_legend_handles_labels()[1].count(
                       "left its slot (landing, landed or stopped)") else None)
        ax.annotate(f"{aid} down at {run.t[k]:.1f} s", rel, fontsize=7, xytext=(5, -9), textcoords="offset points")


def _frame_flying(run: Run, ax: Axes, target: np.ndarray | None) -> None:
    """Limit the relative view to the vehicles' positions while in flight (and the slots), so that a
    landed vehicle far below its leader does not shrink the formation to a dot."""
    fly = flying(run)
    rel = run.p[:, :, :2] - run.leader_p[:, None, :2]
    pts = [rel[fly], np.zeros((1, 2))] + ([target] if target is not None else [])
    xy = np.concatenate(pts)
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if not fly.all() and xy.size:
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        pad = 0.08 * float(max(hi - lo)) + 0.1
        ax.set_aspect("equal", adjustable="box")  # the limits stand, the box takes the aspect
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)


def run_panels(run: Run, out_dir: str | Path, offsets: np.ndarray | None = None) -> list[Path]:
    """Per-run figures: errors and gains (``errors_gains.png``), velocities against the leader's
    (``velocities.png``) and the path in the x-y plane with formation snapshots and target slots,
    beside the same relative to the leader (``xy.png``), and the formation to scale at four times
    (``formation.png``); each with its SVG beside. ``offsets``: the formation's ``h_i`` (default:
    from the run's mission text). One colour per agent in every panel."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return [_save(errors_figure(run), out / "errors_gains.png"),
            _save(velocities_figure(run), out / "velocities.png"),
            _save(xy_figure(run, offsets), out / "xy.png"),
            _save(formation_figure(run, offsets), out / "formation.png")]


def formation_figure(run: Run, offsets: np.ndarray | None = None) -> Figure:
    """The formation to scale at the start, a quarter, half way and the end of the run
    (``formation.png``): :func:`snapshots_figure` at those times, titled with the law."""
    ticks = _snapshot_ticks(run)  # among the ticks recorded (a run cut short lacks the others)
    if not ticks:  # no tick holds every vehicle's position (a recorder killed early): say so
        fig, ax = plt.subplots(figsize=(6.0, 2.0))
        ax.axis("off")
        ax.text(0.5, 0.5, "no recorded tick holds every vehicle's position", ha="center", va="center")
        fig.suptitle(title(run, "the formation to scale"), fontsize=10)
        return fig
    fig = snapshots_figure(run, tuple(float(run.t[k]) for k in ticks), offsets=offsets)
    fig.suptitle(title(run, "the formation to scale (hollow: target slots)"), fontsize=10)
    fig.tight_layout()
    return fig


def heatmaps(rows: list[dict], out_dir: str | Path, *, loss: list[float], delay: list[float], burst: list[float],
             laws: list[str], title: str = "") -> list[Path]:
    """A degradation sweep's maps (``tether sweep``): one figure per burst length, ``heatmap.png``
    or ``heatmap-burst<b>.png``; rows ultimate bound of ``||xi||`` (log colour scale), peak gain
    and divergence, one column per law; loss on the vertical axis, delay on the horizontal one.
    Every cell is labelled with its value."""
    from matplotlib.colors import LogNorm

    out_dir = Path(out_dir)
    paths = []
    for b in burst:
        fig, ax = plt.subplots(3, len(laws), figsize=(4.6 * len(laws) + 1.0, 10.0), squeeze=False)
        grids = {}
        for law in laws:
            cell = {(r["loss_pct"], r["delay_ms"]): r for r in rows if r["law"] == law and r["burst"] == b}
            bound = np.array([[cell[lo, de]["ultimate_bound_m"] if not cell[lo, de]["diverged"] else np.nan
                               for de in delay] for lo in loss])
            gain = np.array([[cell[lo, de]["peak_gain"] for de in delay] for lo in loss])
            div = np.array([[float(cell[lo, de]["diverged"]) for de in delay] for lo in loss])
            grids[law] = (bound, gain, div)
        finite = np.concatenate([g[0][np.isfinite(g[0])] for g in grids.values()] + [np.array([])])
        finite = finite[finite > 0]
        norm = LogNorm(vmin=finite.min(), vmax=max(finite.max(), finite.min() * 1.01)) if finite.size else None
        gains = np.concatenate([g[1][np.isfinite(g[1])].ravel() for g in grids.values()] + [np.array([1.0])])
        for c, law in enumerate(laws):
            bound, gain, div = grids[law]
            panels = ((bound, r"ultimate bound of the true $\|\xi\|$ [m]", "viridis", norm, "{:.3g}"),
                      (gain, r"peak gain max($K_p$, $K_v$)", "magma", None, "{:.3g}"),
                      (div, "diverged", "Reds", None, None))
            for r, (z, label, cmap, nrm, fmt) in enumerate(panels):
                a = ax[r, c]
                kw = {"norm": nrm} if nrm is not None else (
                    {"vmin": 0.0, "vmax": 1.0} if fmt is None else {"vmin": gains.min(), "vmax": gains.max()})
                im = a.imshow(np.ma.masked_invalid(z), origin="lower", aspect="auto", cmap=cmap, **kw)
                for i in range(len(loss)):
                    for j in range(len(delay)):
                        text = ("yes" if z[i, j] else "no") if fmt is None else (
                            "div." if not np.isfinite(z[i, j]) else fmt.format(z[i, j]))
                        rgb = im.cmap(im.norm(z[i, j]))[:3] if np.isfinite(z[i, j]) else (1.0, 1.0, 1.0)
                        light = 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2] > 0.5
                        a.text(j, i, text, ha="center", va="center", fontsize=7, color="black" if light else "white")
                a.set_xticks(range(len(delay)), [f"{d:g}" for d in delay])
                a.set_yticks(range(len(loss)), [f"{lo:g}" for lo in loss])
                a.set_xlabel("one-way delay [ms]")
                a.set_ylabel("loss [%]")
                a.set_title(f"{law}: {label}", fontsize=9)
                if fmt is not None:
                    fig.colorbar(im, ax=a, fraction=0.046)
        burst_note = "independent losses" if b <= 1 else f"loss bursts of {b:g} messages on average"
        fig.suptitle(f"{title}\n{burst_note}" if title else burst_note, fontsize=10)
        fig.tight_layout()
        path = out_dir / ("heatmap.png" if len(burst) == 1 else f"heatmap-burst{b:g}.png")
        paths.append(_save(fig, path))
    return paths


def snapshots_figure(run: Run, times: tuple[float, ...], three_d: bool = False,
                     offsets: np.ndarray | None = None) -> Figure:
    """:func:`snapshots`, unsaved."""
    if offsets is None:
        offsets = mission_offsets(run)
    n = len(run.agent_ids)
    colours = [colour(i) for i in range(n)]
    dt = 1.0 / run.meta.rate
    ks = [min(len(run.t) - 1, int(round(t / dt))) for t in times]
    order = _polygon(offsets[:, :2] if offsets is not None else run.p[ks[0], :, :2])
    if three_d:
        fig = plt.figure(figsize=(7.5, 6.5))
        ax = fig.add_subplot(projection="3d")
        sl = _decimate(run)
        for i, aid in enumerate(run.agent_ids):
            ax.plot(run.p[sl, i, 0], run.p[sl, i, 1], run.p[sl, i, 2], lw=0.7, color=colours[i], label=f"agent {aid}")
        ax.plot(run.leader_p[sl, 0], run.leader_p[sl, 1], run.leader_p[sl, 2], "k--", lw=0.8, label="leader")
        if run.plant.payload_p is not None:
            pp = run.plant.payload_p[sl]
            ax.plot(pp[:, 0], pp[:, 1], pp[:, 2], color="tab:brown", lw=1.2, label="payload")
        for n_snap, k in enumerate(ks):
            first = n_snap == 0
            ring = _ring(run.p[k], order)
            ax.plot(ring[:, 0], ring[:, 1], ring[:, 2], "k:", lw=0.8, label="formation" if first else None)
            ax.scatter(run.p[k, :, 0], run.p[k, :, 1], run.p[k, :, 2], marker="^", c=colours)
            if offsets is not None:
                slots = run.leader_p[k] + offsets
                sring = _ring(slots, order)
                ax.plot(sring[:, 0], sring[:, 1], sring[:, 2], "--", lw=0.7, color="0.55",
                        label="target formation" if first else None)
                ax.scatter(slots[:, 0], slots[:, 1], slots[:, 2], s=50, facecolors="none", edgecolors=colours,
                           label="target slots" if first else None)
            ax.scatter(*run.leader_p[k], marker="*", s=80, color="k")
            ax.text(*run.leader_p[k], f" t={run.t[k]:.0f}s", fontsize=7)
        pts = np.concatenate([run.p.reshape(-1, 3), run.leader_p])
        ext = np.nanmax(pts, axis=0) - np.nanmin(pts, axis=0)
        if max(ext) <= ASPECT_LIMIT * max(min(ext), 1e-9):
            ax.set_box_aspect(tuple(float(e) for e in ext))  # to scale
        else:
            ax.set_title("not to scale: " + ", ".join(f"{a} spans {e:.3g} m" for a, e in zip(AXES, ext)), fontsize=8)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        ax.legend(fontsize=7)
    else:
        fig, axs = plt.subplots(1, len(ks), figsize=(3.6 * len(ks), 3.8), squeeze=False)
        lo = np.nanmin(np.concatenate([run.p[:, :, :2].reshape(-1, 2), run.leader_p[:, :2]]), axis=0) - 0.3
        hi = np.nanmax(np.concatenate([run.p[:, :, :2].reshape(-1, 2), run.leader_p[:, :2]]), axis=0) + 0.3
        spread = float(np.nanmax(np.ptp(run.p[ks][:, :, :2], axis=1))) + 0.6 if ks else 1.0
        spread = spread if np.isfinite(spread) else 1.0
        follow = float(np.max(hi - lo)) > 10 * spread  # a long mission: each panel centred on its leader
        for ax, k in zip(axs[0], ks):
            lead = run.leader_p[k, :2]
            if offsets is not None:
                slots = lead + offsets[:, :2]
                ax.plot(*_ring(slots, order).T, "--", lw=0.7, color="0.55")
                ax.scatter(slots[:, 0], slots[:, 1], s=90, facecolors="none", edgecolors=colours, lw=1.0)
            ax.plot(*_ring(run.p[k, :, :2], order).T, "k:", lw=0.8)
            ax.scatter(run.p[k, :, 0], run.p[k, :, 1], marker="^", s=50, c=colours, zorder=3)
            for i, aid in enumerate(run.agent_ids):
                ax.annotate(str(aid), run.p[k, i, :2], fontsize=7, xytext=(3, 3), textcoords="offset points")
            ax.plot(lead[0], lead[1], "*", ms=12, color="k")
            ax.set_title(f"t = {run.t[k]:.0f} s", fontsize=9)
            if follow:
                ax.set_xlim(lead[0] - spread, lead[0] + spread)
                ax.set_ylim(lead[1] - spread, lead[1] + spread)
            else:
                ax.set_xlim(lo[0], hi[0])
                ax.set_ylim(lo[1], hi[1])
            ax.set_aspect("equal")
            ax.grid(True, lw=0.3)
            ax.set_xlabel("x [m]")
        axs[0, 0].set_ylabel("y [m]")
    fig.tight_layout()
    return fig


def snapshots(run: Run, times: tuple[float, ...], path: str | Path, three_d: bool = False,
              offsets: np.ndarray | None = None) -> Path:
    """Figs. 7 and 10: the vehicles (triangles, the agent's colour) and the leader (star) at
    ``times``, the formation's polygon dotted, the target slots (leader + ``h_i``, hollow) and
    their polygon dashed; one panel per time in the x-y plane (to scale), or one 3D panel with
    every time (to scale unless its extents differ too much, then said in the title)."""
    return _save(snapshots_figure(run, times, three_d, offsets), path)


def _polygon(xy: np.ndarray) -> np.ndarray:
    """Indices ordering points around their centroid (to draw a formation's outline)."""
    c = xy.mean(axis=0)
    return np.argsort(np.arctan2(xy[:, 1] - c[1], xy[:, 0] - c[0]))


def variants(runs: dict[str, Run], path: str | Path, offsets: np.ndarray, title: str = "") -> Path:
    """One line per run: max_i ||xi_i|| and the tracking error max_i ||p_i - h_i - p_leader|| over time."""
    path = Path(path)
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    for label, run in runs.items():
        sl = _decimate(run)
        a0.plot(run.t[sl], np.nanmax(metrics.xi_norm(run)[sl], axis=1), lw=0.9, label=label)
        e = run.p - offsets[None] - run.leader_p[:, None, :]
        a1.plot(run.t[sl], np.nanmax(np.linalg.norm(e[sl], axis=2), axis=1), lw=0.9, label=label)
    a0.set_ylabel(r"max$_i\,\|\xi_i\|$ [m]")
    a1.set_ylabel("tracking error [m]")
    a1.set_xlabel("t [s]")
    for a in (a0, a1):
        a.set_yscale("log")
        a.grid(True, lw=0.3, which="both")
    a0.legend(fontsize=7)
    if title:
        a0.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


def payload(run: Run, path: str | Path, mass: float) -> Path:
    """The payload's path against the leader's, and the cable tensions against the weight share."""
    path = Path(path)
    rec = run.plant
    if rec.payload_p is None or rec.tension is None:
        raise ValueError("the run has no payload record")
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    sl = _decimate(run)
    for k in range(3):
        a0.plot(run.t[sl], rec.payload_p[sl, k], lw=1.0, label=f"payload {AXES[k]}")
        a0.plot(run.t[sl], run.leader_p[sl, k], "--", lw=0.8, color=f"C{k}", alpha=0.6, label=f"leader {AXES[k]}")
    a0.set_ylabel("position [m]")
    a0.legend(fontsize=7, ncol=3)
    for i, aid in enumerate(run.agent_ids):
        a1.plot(run.t[sl], rec.tension[sl, i], lw=0.8, label=f"cable {aid}")
    a1.axhline(mass * 9.81 / len(run.agent_ids), color="k", ls=":", lw=0.8, label="weight / N")
    mark_events(run, (a0, a1))
    a1.set_ylabel("tension [N]")
    a1.set_xlabel("t [s]")
    a1.legend(fontsize=7, ncol=3)
    for a in (a0, a1):
        a.grid(True, lw=0.3)
    fig.tight_layout()
    return _save(fig, path)
