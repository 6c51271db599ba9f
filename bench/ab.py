"""Two checkouts of tether side by side: the same ``tether run`` from this tree and from a git
revision, alternating, every pair in one sitting.

    .venv/bin/python bench/ab.py --base HEAD~1                          # section4, lockstep, 100 s, 5 pairs
    .venv/bin/python bench/ab.py --base 4c4340b~1 --pairs 7 --duration 200 -- --network star

This tree, with whatever it has not committed, is *new* (or ``--new REV``, to measure a past change
against its parent); ``--base`` is checked out into a temporary git worktree, removed at the end.
Both run ``tether run MISSION --no-mcap`` (with ``--mcap``: writing ``run.mcap``; and the options
after ``--``) as ``python -m cli`` from inside their own checkout (``bench/runtime.py``'s ``run_tether``
with ``tree``): ``-m`` puts the working directory first on the path and the children inherit it, so
the launcher and every process it starts import that checkout, not the installed one. Each run then
checks where its processes ran, and stops the comparison if any ran elsewhere. Running the base with
only ``PYTHONPATH`` pointing at it, from this tree's directory, would measure this tree twice.

Per run, from ``/proc`` over the run's window (as ``bench/runtime.py``): speed (mission s per wall
s), CPU per tick of all processes, of the median process of each role and of its main (asyncio)
thread, and the CPU other users took meanwhile. The pairs alternate which side runs first, and each
run waits for the machine to be quiet. Printed: every run, then each figure's median per side, new /
base, and in how many pairs new did better. Only figures of one sitting compare: machines differ.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from bench import runtime as rt  # noqa: E402
from bench import worktree  # noqa: E402
from tether import catalog  # noqa: E402
from tether.node import load_mission  # noqa: E402

ROLES = ("agent", "recorder", "launcher", "leader", "plant", "world")

FIGURES: list[tuple[str, str, bool]] = [
    ("speed", "speed [x real time]", True),
    ("command_s", "the whole command [s]", False),
    ("end_s", "from the last tick to the exit [s]", False),
    ("cpu_us", "CPU per tick, all processes [us]", False),
    *[(f"{ro}_us", f"{ro}, median process [us per tick]", False) for ro in ROLES],
    *[(f"{ro}_main_us", f"{ro}, its main thread [us per tick]", False) for ro in ROLES],
]
"""(key, label, higher is better) of each figure compared."""


def measure(res: rt.Result, ticks: float) -> dict[str, float]:
    """The figures of one run (NaN where its role did not run)."""
    per = rt._per_tick(res, ticks, ROLES)  # noqa: SLF001 - the bench's own helper
    out = {"speed": res.speed if res.ran_to_end else float("nan"),
           "command_s": res.command_s, "end_s": res.end_s, "cpu_us": per["total_us"], "foreign_pct": res.foreign_pct}
    for ro in ROLES:
        out[f"{ro}_us"], out[f"{ro}_main_us"] = per[ro]["us"], per[ro]["main"]
    return out


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    extra: list[str] = []
    if "--" in argv:
        at = argv.index("--")
        argv, extra = argv[:at], argv[at + 1:]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 epilog="options after -- go to both runs' tether run")
    ap.add_argument("--base", required=True, help="the git revision to compare this tree with (e.g. HEAD~1)")
    ap.add_argument("--new", help="a git revision in this tree's place (to measure a past change against its parent)")
    ap.add_argument("--pairs", type=int, default=5)
    ap.add_argument("--mission", default="section4")
    ap.add_argument("--duration", type=float, default=100.0, help="mission seconds per run")
    ap.add_argument("--clock", choices=("lockstep", "realtime"), default="lockstep")
    ap.add_argument("--insecure", action="store_true", help="both runs with tether run --insecure")
    ap.add_argument("--mcap", action="store_true", help="both runs write run.mcap (default: --no-mcap)")
    ap.add_argument("--json", type=Path, help="also write every run's figures here")
    a = ap.parse_args(argv)
    if a.pairs < 1 or not a.duration > 0:
        ap.error("--pairs must be at least 1 and --duration positive")
    for flag, rev in (("--base", a.base), ("--new", a.new)):
        if rev is not None and not worktree.is_commit(rev):
            ap.error(f"{flag} {rev}: not a commit of this repository (give a revision such as HEAD~1 or a hash)")
    try:
        path = catalog.resolve(a.mission)
        m = load_mission(path, a.duration)
    except Exception as exc:  # noqa: BLE001 - said as the CLI says it, before anything runs
        ap.error(f"--mission {a.mission}: {exc}")
    ticks = m.steps + 1
    with tempfile.TemporaryDirectory(prefix="tether-ab-") as tmp:
        work = Path(tmp)
        with worktree.checked_out(a.base, work / "base") as base, worktree.checked_out(a.new, work / "new") as new:
            for tree in (new, base):
                rt.compile_tree(tree)  # as an installed package has its bytecode, both sides alike
            rt.say(f"bench/ab.py: {a.mission} ({m.n} agents, {m.rate:g} Hz), {a.clock}, {a.duration:g} s per run, "
                   f"{a.pairs} pairs; new: {'this tree' if a.new is None else a.new} ({worktree.short(new)}"
                   f"{', with what it has not committed' if a.new is None else ''}); base: {a.base} "
                   f"({worktree.short(base)}); "
                   f"tether run options: {' '.join(extra) or '(none)'}")
            runs: dict[str, list[dict[str, float]]] = {"base": [], "new": []}
            for i in range(a.pairs):
                order = ("base", "new") if i % 2 == 0 else ("new", "base")
                for side in order:
                    tree = base if side == "base" else new
                    rt.settle()
                    res = rt.run_tether(path, m, a.clock, a.duration, work, tree=tree, extra=tuple(extra),
                                        secure=not a.insecure, mcap=a.mcap)
                    want = {str(tree)}
                    if res.cwds != want:
                        raise SystemExit(f"bench/ab.py: the {side} run's processes ran in {sorted(res.cwds)}, "
                                         f"not {sorted(want)}: the comparison would not be of the two trees")
                    if not res.ran_to_end:
                        raise SystemExit(f"bench/ab.py: the {side} run failed: {res.why}")
                    fig = measure(res, ticks)
                    runs[side].append(fig)
                    rt.say(f"   pair {i + 1} {side:4}  {fig['speed']:6.2f} x  command {fig['command_s']:6.2f} s "
                           f"(after the last tick {fig['end_s']:5.2f})  CPU/tick {fig['cpu_us']:7.0f} us  agent "
                           f"{fig['agent_us']:5.0f} (main {fig['agent_main_us']:4.0f})  recorder {fig['recorder_us']:5.0f} "
                           f"(main {fig['recorder_main_us']:4.0f}) us  other users {fig['foreign_pct']:3.0f} %"
                           + (" NOISY" if fig["foreign_pct"] >= rt.NOISY else "")
                           + (f" (exit 5: {res.complete} samples recorded)" if res.status == 5 else ""))
    report(runs)
    if a.json:
        a.json.write_text(json.dumps({"base": a.base, "mission": a.mission, "duration": a.duration,
                                      "clock": a.clock, "extra": extra, "runs": runs}, indent=1))


def report(runs: dict[str, list[dict[str, Any]]]) -> None:
    """Each figure's median per side, new / base, and in how many pairs new did better, over the
    pairs whose two runs were quiet (other users under ``bench/runtime.py``'s NOISY), or over every
    pair if none was."""
    both = list(zip(runs["base"], runs["new"]))
    quiet = [(x, y) for x, y in both if max(x["foreign_pct"], y["foreign_pct"]) < rt.NOISY] or both
    rt.say(f"   over {len(quiet)} of {len(both)} pairs (the others noisy)" if len(quiet) < len(both) else
           f"   over all {len(both)} pairs")
    rt.say(f"   {'figure':42} {'base':>9} {'new':>9} {'new/base':>9}  new better in")
    for key, label, higher in FIGURES:
        b, n = rt.med([x[key] for x, _ in quiet]), rt.med([y[key] for _, y in quiet])
        if b != b and n != n:
            continue  # a role this mission does not run
        pairs = [(x[key], y[key]) for x, y in quiet if x[key] == x[key] and y[key] == y[key]]
        better = sum(1 for x, y in pairs if (y > x if higher else y < x))
        rt.say(f"   {label:42} {b:>9.2f} {n:>9.2f} {rt.ratio(n, b):>9.3f}  {better} of {len(pairs)}")


if __name__ == "__main__":
    main()
