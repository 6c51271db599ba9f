"""``tether report``, and the ``report.html`` every run and study writes (``recorder/report.py``
builds the page; this module gathers what goes on it from a run's directory)."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

from cli.args import BadArgument

if TYPE_CHECKING:
    from tether.runfile import Run

NAME = "report.html"
OUTCOME = "outcome.json"
"""Where ``tether run`` leaves its exit status and its meaning (``deploy/outcome.py``)."""

CAPTIONS = {
    "errors_gains": "True formation error (Eq. 8 from the vehicles' positions), tracking error (distance from "
                    "the slot), the agents' own ‖ξ_i‖ and the gains; a long run as min/max envelopes with its "
                    "first and last seconds zoomed; safety events numbered.",
    "velocities": "Each agent's velocity against the leader's.",
    "xy": "Paths with formation snapshots and target slots; beside, positions relative to the leader, framed on "
          "the vehicles in flight (X: where a vehicle left its slot).",
    "formation": "The formation to scale at the start, a quarter, half way and the end (hollow circles: the "
                 "target slots).",
}


def add_parser(sub: argparse._SubParsersAction) -> None:
    rp = sub.add_parser("report", help="write a run's or a study's report.html again (one self-contained page)")
    rp.add_argument("run", help="a run's directory (run.npz), a run.npz, or a study's directory (sweep.md)")
    rp.add_argument("--out", default=None, help="the page (default: report.html in the run's directory)")
    rp.set_defaults(func=cmd_report)


def _json_list(path: Path) -> list[dict]:
    """A JSON list of objects from ``path``; empty if absent or unreadable (said on stderr)."""
    if not path.exists():
        return []
    try:
        rows = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        print(f"warning: {path} is not readable JSON ({exc}); the report leaves it out", file=sys.stderr)
        return []
    return [r for r in rows if isinstance(r, dict)] if isinstance(rows, list) else []


def outcome_of(out: Path) -> tuple[int, str] | None:
    """The exit status ``tether run`` left in ``out`` (:data:`OUTCOME`), or None."""
    try:
        doc = json.loads((out / OUTCOME).read_text())
        return int(doc["exit_status"]), str(doc["meaning"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def write_run(out: Path, run: Run, *, drawn: list[Path] | None = None, status: tuple[int, str] | None = None,
              notes: tuple[str, ...] = (), page: Path | None = None) -> Path:
    """Write ``out/report.html`` for ``run``: its metrics, its figures (``drawn``, or drawn now with
    their SVGs beside), the events and faults ``out`` holds and the exit status (``status``, or the
    one ``out`` holds). Returns the page's path."""
    import numpy as np

    from recorder import report
    from sim import figures, metrics
    from tether import jsonout, safefs

    values = jsonout.finite(metrics.report(run))
    assert isinstance(values, dict)
    if drawn is None:
        drawn = figures.run_panels(run, out)
    shown = [(p.stem, p.read_bytes(), CAPTIONS.get(p.stem, p.stem)) for p in drawn if p.exists()]
    geo = metrics.geometry(run)
    with warnings.catch_warnings():  # ticks a recorder lacks are all-NaN rows: drawn as gaps
        warnings.simplefilter("ignore", RuntimeWarning)
        if geo is not None:
            worst, label = np.nanmax(metrics.true_xi_norm(run, geo), axis=1), "max_i true formation error ‖ξ_i‖"
        else:
            worst, label = np.nanmax(metrics.xi_norm(run), axis=1), "max_i agents' own ‖ξ_i‖"
    text = report.run_page(run, values, shown, status=status or outcome_of(out),
                           launcher_events=[e for e in _json_list(out / "events.json") if e.get("what") != "back"
                                            and not (e.get("what") == "failsafe"
                                                     and str(e.get("who", "")).startswith("agent/"))],
                           faults=_json_list(out / "faults.json"), worst=worst, worst_label=label, notes=notes)
    target = page or out / NAME
    safefs.write_file(target, text.encode())
    return target


def write_study(out: Path, markdown: str = "sweep.md") -> Path | None:
    """Write ``out/report.html`` from a study's Markdown report and the figures it names; None when
    ``out`` holds no such report."""
    from recorder import report
    from tether import safefs

    md = out / markdown
    if not md.exists():
        return None
    images = {p.name: p.read_bytes() for p in out.glob("*.png")}
    target = out / NAME
    safefs.write_file(target, report.study_page(md.read_text(), images).encode())
    return target


def cmd_report(args: argparse.Namespace) -> int:
    from recorder import journal

    path = Path(args.run)
    if not path.exists():
        raise BadArgument(f"run: {path} does not exist; give a run's directory (tether simulate/run --out DIR), "
                          "its run.npz, or a study's directory")
    folder = path if path.is_dir() else path.parent
    if path.is_dir() and not (path / "run.npz").exists() and not (path / journal.NAME).exists():
        page = write_study(path)
        if page is None:
            raise BadArgument(f"run: {path} holds no run.npz, no journal and no sweep.md; give a run's or a "
                              "study's directory")
        print(f"wrote {page}")
        return 0
    try:
        run = journal.load(path, report=lambda line: print(f"missing: {line}"))
    except (OSError, ValueError) as exc:
        raise BadArgument(f"run: {path} holds no readable run ({exc}); give a run.npz or the directory "
                          "tether run --out wrote") from None
    page = write_run(folder, run, page=Path(args.out) if args.out else None)
    print(f"wrote {page}")
    return 0
