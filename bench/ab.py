"""Two checkouts of tether side by side: the same ``tether run`` from this tree and from a git
revision, alternating, every pair in one run of this script.

    .venv/bin/python bench/ab.py --base HEAD~1                          # section4, lockstep, 100 s, 5 pairs
    .venv/bin/python bench/ab.py --base 4c4340b~1 --pairs 7 --duration 200 -- --network star
    .venv/bin/python bench/ab.py --base HEAD --mixed --clock realtime --mission RING.toml --duration 30

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
base, and in how many pairs new did better. Only figures of one run of this script compare: machines differ.

``--mixed`` compares the vehicles' processes (agent and plant) within one swarm instead: half of them
from each checkout in every run, swapped from run to run (:func:`mixed`). Two runs one after the other
differ by more than a change of a few per cent (an agent's CPU per tick drifted by a quarter within
one run of 6 pairs); two halves of one run see the same machine at every instant.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from bench import procstat  # noqa: E402
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


def measure(res: procstat.Result, ticks: float) -> dict[str, float]:
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
    ap.add_argument("--mixed", action="store_true",
                    help="one swarm per run, half its vehicles (agent and plant) from each checkout, swapped from "
                         "run to run: the two sides share every moment of the machine (--pairs runs)")
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
    if a.mixed and (m.n < 2 or any(x.startswith("--wrap") for x in extra)):
        ap.error("--mixed: needs a mission of at least two agents, and takes no --wrap of its own")
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
            if a.mixed:
                mixed_runs = mixed(a, path, m, extra, base, new, work)
                if a.json:
                    a.json.write_text(json.dumps({"base": a.base, "mission": a.mission, "duration": a.duration,
                                                  "clock": a.clock, "extra": extra, "mixed": mixed_runs}, indent=1))
                return
            runs: dict[str, list[dict[str, float]]] = {"base": [], "new": []}
            for i in range(a.pairs):
                order = ("base", "new") if i % 2 == 0 else ("new", "base")
                for side in order:
                    tree = base if side == "base" else new
                    rt.settle()
                    res = rt.run_tether(path, m, a.clock, a.duration, work, tree=tree, extra=tuple(extra),
                                        secure=not a.insecure, mcap=a.mcap)
                    checked(res, {tree}, f"the {side} run")
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


def checked(res: procstat.Result, trees: set[Path], what: str) -> None:
    """Stop the comparison unless ``res`` went to its end and its processes ran in exactly ``trees``
    (each process imports the checkout it runs in)."""
    want = {str(t) for t in trees}
    if res.cwds != want:
        raise SystemExit(f"bench/ab.py: {what}'s processes ran in {sorted(res.cwds)}, not {sorted(want)}: the "
                         "comparison would not be of the two trees")
    if not res.ran_to_end:
        raise SystemExit(f"bench/ab.py: {what} failed: {res.why}")


MIXED_FIGURES = (("agent", "us"), ("agent", "main"), ("agent", "callback"), ("agent", "zenoh"), ("plant", "us"),
                 ("plant", "main"))
"""(role, what) compared by ``--mixed``: a process's CPU [us per tick], or its threads' of that kind."""


def mixed(a: argparse.Namespace, path: Path, m: Any, extra: list[str], base: Path, new: Path,
          work: Path) -> list[dict[str, Any]]:
    """``--mixed``: ``a.pairs`` runs of one swarm each, its vehicles alternately from either checkout
    (``--wrap ID='env -C TREE'``: the agent and the plant of a vehicle start in that checkout and
    import it; the launcher, leader and recorder from the new one), every other run the other way
    round, so that a vehicle's place in the graph cancels out. Both sides see the same machine at
    every instant: what separates two sequential runs (other users, the machine's state drifting
    from minute to minute) is common to both. Per run and side: the median vehicle's CPU per tick.
    Printed: each run, then per figure the median over runs of new / base and in how many runs new
    did better."""
    ids = sorted(x.id for x in m.agents)
    ticks = m.steps + 1
    out: list[dict[str, Any]] = []
    for r in range(a.pairs):
        side = {nid: ("base", "new")[(n + r) % 2] for n, nid in enumerate(ids)}
        wrap = [f"--wrap={nid}=env -C {shlex.quote(str(base if s == 'base' else new))}" for nid, s in side.items()]
        rt.settle()
        res = rt.run_tether(path, m, a.clock, a.duration, work, tree=new, extra=(*extra, *wrap),
                            secure=not a.insecure, mcap=a.mcap)
        checked(res, {base, new}, f"mixed run {r + 1}")
        f = 1e6 / ticks  # CPU seconds over the window -> us per tick (as bench/runtime.py's _per_tick)
        row: dict[str, Any] = {"foreign_pct": res.foreign_pct}
        for s_ in ("base", "new"):
            for ro, what in MIXED_FIGURES:
                procs = [p for p in res.procs if p.role == ro and side.get(p.nid) == s_]
                vals = [p.cpu if what == "us" else p.by_thread()[what] for p in procs]
                row[f"{s_}:{ro}_{what}"] = procstat.med(vals) * f if vals else float("nan")
        out.append(row)
        rt.say(f"   run {r + 1} (base: {' '.join(str(n) for n, s_ in side.items() if s_ == 'base')})  agent "
               f"{row['base:agent_us']:6.0f} -> {row['new:agent_us']:6.0f} us (main {row['base:agent_main']:5.0f} -> "
               f"{row['new:agent_main']:5.0f})  plant {row['base:plant_us']:6.0f} -> {row['new:plant_us']:6.0f} us  "
               f"other users {res.foreign_pct:3.0f} %" + (" NOISY" if res.foreign_pct >= rt.NOISY else ""))
    rt.say(f"   over {len(out)} runs, per tick of the window's CPU per vehicle process (median vehicle of each side)")
    rt.say(f"   {'figure':32} {'base':>9} {'new':>9} {'new/base (median of runs)':>27}  new better in")
    for ro, what in MIXED_FIGURES:
        key = f"{ro}_{what}"
        pairs = [(x[f"base:{key}"], x[f"new:{key}"]) for x in out]
        pairs = [(b, n) for b, n in pairs if b == b and n == n]
        if not pairs:
            continue
        label = f"{ro}, {'process' if what == 'us' else what + ' thread(s)'} [us]"
        rt.say(f"   {label:32} {procstat.med([b for b, _ in pairs]):>9.1f} {procstat.med([n for _, n in pairs]):>9.1f} "
               f"{procstat.med([n / b for b, n in pairs]):>27.3f}  {sum(1 for b, n in pairs if n < b)} of {len(pairs)}")
    return out


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
        b, n = procstat.med([x[key] for x, _ in quiet]), procstat.med([y[key] for _, y in quiet])
        if b != b and n != n:
            continue  # a role this mission does not run
        pairs = [(x[key], y[key]) for x, y in quiet if x[key] == x[key] and y[key] == y[key]]
        better = sum(1 for x, y in pairs if (y > x if higher else y < x))
        rt.say(f"   {label:42} {b:>9.2f} {n:>9.2f} {procstat.ratio(n, b):>9.3f}  {better} of {len(pairs)}")


if __name__ == "__main__":
    main()
