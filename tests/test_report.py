"""``report.html`` (``recorder/report.py``, ``cli/report.py``) opened in a real headless Chromium,
and what ``tether simulate`` and ``tether run`` say of what they computed: what a mission asks for
that the simulator does not fly, a held ``--out``, a stalled host in lockstep, an interrupted run."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from sim import refsim
from tether import catalog
from tether import mission as ms
from tether.runfile import Run
from tests.support import finish, kill, tether, tether_popen, wait_until

CHROMIUM = "chromium"


def chromium(page: Path, profile: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """Open ``page`` in headless Chromium, offline (no network services), with its console on stderr."""
    exe = shutil.which(CHROMIUM)
    assert exe, "the report's tests need Debian's chromium (apt-get install -y chromium; .ci/run installs it)"
    return subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                           "--disable-component-update", "--disable-sync", "--no-first-run",
                           f"--user-data-dir={profile}", "--enable-logging=stderr", "--v=0",
                           "--virtual-time-budget=10000", *args, page.as_uri()],
                          capture_output=True, text=True, timeout=180)


def check_in_browser(page: Path, tmp_path: Path, figures: int) -> str:
    """The page opens, every figure decodes, no script error and no console error; its DOM."""
    done = chromium(page, tmp_path / "profile", "--dump-dom")
    assert done.returncode == 0, done.stderr[-2000:]
    body = re.search(r"<body[^>]*>", done.stdout)
    assert body, done.stdout[:500]
    assert f'data-figures="{figures}/{figures}"' in body.group(0), body.group(0)
    assert "data-errors" not in body.group(0), body.group(0)
    console = [ln for ln in done.stderr.splitlines() if "CONSOLE" in ln]
    assert not console, console
    # self-contained: nothing it would fetch
    text = page.read_text()
    assert not re.search(r"""(src|href)=['"](https?:)?//""", text)
    return done.stdout


@pytest.mark.slow  # a simulation, figures and a browser
def test_simulate_writes_a_report_that_opens_in_chromium(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    done = tether("simulate", "section4", "--duration", "20", "--out", str(out), "--no-mcap")
    assert done.returncode == 0, done.stderr
    values = json.loads((out / "metrics.json").read_text())
    dom = check_in_browser(out / "report.html", tmp_path, 4)
    for text in ("section4: law sigma", "true formation error", "tracking_error_m",
                 f"{values['tracking_error_m']:.4g}", f"{values['formation_error_bound_m']:.4g}", "Agents and graph"):
        assert text in dom, text
    assert dom.count("<svg") == 1  # the timeline
    shot = tmp_path / "shot.png"
    done = chromium(out / "report.html", tmp_path / "profile2", "--hide-scrollbars", "--window-size=1200,1600",
                    f"--screenshot={shot}")
    assert done.returncode == 0 and shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and shot.stat().st_size > 50_000
    # tether report writes it again from the run directory
    (out / "report.html").unlink()
    again = tether("report", str(out))
    assert again.returncode == 0, again.stderr
    assert "formation_error_bound_m" in (out / "report.html").read_text()


@pytest.mark.slow  # two simulations (exp2 compiles its payload world)
def test_simulate_says_what_it_does_not_fly(tmp_path: Path) -> None:
    """exp2 has a payload and quadrotors: the reference simulator flies the law alone and says so, in
    one line, in metrics.json and on the report."""
    out = tmp_path / "exp2"
    done = tether("simulate", "exp2", "--duration", "0.5", "--out", str(out), "--no-mcap", "--no-figures")
    assert done.returncode == 0, done.stderr
    said = [ln for ln in done.stderr.splitlines() if "flies the law alone" in ln]
    assert len(said) == 1 and "payload" in said[0] and "QuadrotorPlant" in said[0] and "tether run" in said[0], \
        done.stderr
    values = json.loads((out / "metrics.json").read_text())
    assert any("payload" in x for x in values["not_flown"])
    assert "flies the law alone" in (out / "report.html").read_text()
    plain = tether("simulate", "section4", "--duration", "0.5", "--out", str(tmp_path / "s4"), "--no-mcap",
                   "--no-figures")
    assert "flies the law alone" not in plain.stderr and "not_flown" not in (tmp_path / "s4" / "metrics.json").read_text()


@pytest.mark.slow  # a simulation
def test_a_netem_mission_is_said_not_flown(tmp_path: Path) -> None:
    """A sweep cell's own mission (30 % loss, 100 ms): simulate names [netem] (before, it flew the ideal
    network without a word)."""
    text = catalog.builtin_path("section4").read_text() + "\n[netem]\ndefault = { delay = { constant = 0.1 }, loss = { kind = \"bernoulli\", p = 0.3 } }\n"
    mission = tmp_path / "cell.toml"
    mission.write_text(text)
    ms.load(mission)  # the mission is valid
    done = tether("simulate", str(mission), "--duration", "0.5", "--out", str(tmp_path / "o"), "--no-mcap",
                  "--no-figures")
    assert done.returncode == 0, done.stderr
    assert "[netem]" in done.stderr and "flies the law alone" in done.stderr, done.stderr


def _up(log: Path) -> bool:
    return log.exists() and "processes are up" in log.read_text()


@pytest.mark.slow  # real processes
def test_run_writes_its_report_and_refuses_its_out_while_it_runs_and_after(tmp_path: Path) -> None:
    out = tmp_path / "run"
    log = tmp_path / "first.log"
    first = tether_popen("run", "section4", "--duration", "40", "--out", str(out), "--quiet", "--insecure",
                         "--ns", f"rep-{os.getpid()}", log=log)
    try:
        wait_until(lambda: _up(log), 300, "the first run's processes")
        second = tether("run", "section4", "--duration", "1", "--out", str(out), "--quiet", "--insecure",
                        "--replace", "--ns", f"rep2-{os.getpid()}")
        assert second.returncode == 2 and "--out" in second.stderr and "going on now" in second.stderr, second.stderr
        assert "Traceback" not in second.stderr
        assert first.wait(600) == 0, log.read_text()[-3000:]
    finally:
        kill(first)
    assert json.loads((out / "outcome.json").read_text()) == {"exit_status": 0, "meaning": "clean"}
    for name in ("metrics.json", "errors_gains.png", "errors_gains.svg", "formation.png", "xy.svg", "report.html"):
        assert (out / name).exists(), name
    dom = check_in_browser(out / "report.html", tmp_path, 4)
    assert "exit status 0: clean" in dom and "Links" in dom and "leader → agent 1" in dom
    again = tether("run", "section4", "--duration", "1", "--out", str(out), "--quiet", "--insecure")
    assert again.returncode == 2 and "--out" in again.stderr and "--replace" in again.stderr, again.stderr
    assert Run.load(out).t[-1] == pytest.approx(40.0)  # untouched
    replaced = tether("run", "section4", "--duration", "1", "--out", str(out), "--quiet", "--insecure",
                      "--replace", "--ns", f"rep3-{os.getpid()}")
    assert replaced.returncode == 0, replaced.stderr[-3000:]
    assert Run.load(out).t[-1] == pytest.approx(1.0)


STALL = 1.5
"""How long agent 2's process is stopped [s]: a lease and a half, so its token lapses and comes back."""


def child_of(parent: int, *words: str) -> int | None:
    """The pid of a child of ``parent`` whose command line holds every one of ``words``, or None."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            argv = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        args = [a.decode(errors="replace") for a in argv]
        if ppid == parent and all(w in args for w in words):
            return int(entry.name)
    return None


@pytest.mark.slow  # real processes
def test_a_lockstep_run_whose_host_stalled_ends_clean_with_a_warning(tmp_path: Path) -> None:
    """Agent 2's process starved for three leases (stopped, as a loaded host stops it): its token goes
    and comes back, lockstep waits for it, every tick is recorded and equals the reference simulator:
    exit 0 with a warning, where it was exit 4."""
    out = tmp_path / "run"
    log = tmp_path / "run.log"
    proc = tether_popen("run", "section4", "--duration", "150", "--out", str(out), "--quiet", "--insecure",
                        "--lease", "1", "--network", "star", "--ns", f"stall-{os.getpid()}", log=log)
    try:
        wait_until(lambda: _up(log), 300, "the run's processes")
        agent = wait_until(lambda: child_of(proc.pid, "agent", "--id", "2"), 30, "agent 2's process")
        os.kill(agent, signal.SIGSTOP)
        try:
            time.sleep(STALL)  # the stimulus (a stall this long), not a wait for a condition
        finally:
            os.kill(agent, signal.SIGCONT)
        status = proc.wait(900)
    finally:
        kill(proc)
    text = log.read_text()
    events = json.loads((out / "events.json").read_text())
    assert any(e["what"] == "froze" for e in events), events  # the stall was seen
    assert status == 0, text[-3000:]
    assert "the host stalled" in text
    run = Run.load(out)
    m = ms.with_duration(ms.load(catalog.builtin_path("section4")), 150.0, "section4")
    ref = refsim.simulate(m)
    for f in ("p", "v", "kp", "kv", "xi"):
        assert np.array_equal(getattr(run, f), getattr(ref, f)), f  # bit for bit


@pytest.mark.slow  # real processes
def test_ctrl_c_during_start_up_says_nothing_was_recorded(tmp_path: Path) -> None:
    out = tmp_path / "run"
    proc = tether_popen("run", "section4", "--duration", "5", "--out", str(out), "--insecure",
                        "--ns", f"early-{os.getpid()}")
    try:
        # the launcher's router is up, its processes are not: interrupted while starting
        wait_until(lambda: (out / "logs" / "recorder-0.log").exists(), 120, "the processes' logs", proc)
        proc.send_signal(signal.SIGINT)
        status, text = finish(proc, 300)
    finally:
        kill(proc)
    if "processes are up" in text:
        pytest.skip("every process came up before the interrupt arrived (nothing to judge)")
    assert status == 130, text[-3000:]
    assert "interrupted before the first tick: nothing was recorded" in text, text[-3000:]
    assert "no readable run file" not in text


@pytest.mark.slow  # real processes
def test_an_interrupted_run_reports_what_was_recorded(tmp_path: Path) -> None:
    out = tmp_path / "run"
    log = tmp_path / "run.log"
    proc = tether_popen("run", "section4", "--duration", "300", "--out", str(out), "--quiet", "--insecure",
                        "--ns", f"cut-{os.getpid()}", log=log)
    try:
        wait_until(lambda: _up(log), 300, "the run's processes")
        journal = out / "journal.mcap"
        wait_until(lambda: journal.exists() and journal.stat().st_size > 200_000, 300, "some ticks journalled")
        proc.send_signal(signal.SIGINT)
        status = proc.wait(600)
    finally:
        kill(proc)
    assert status == 130, log.read_text()[-3000:]
    run = Run.load(out)
    planned = len(run.t)
    got = int(np.any(run.safety.safety_mode >= 0, axis=1).sum())
    assert 0 < got < planned
    done = tether("mcap", str(out), "--out", str(tmp_path / "cut.mcap"))
    assert done.returncode == 0, done.stderr
    assert f"{got} of {planned} planned ticks recorded" in done.stdout, done.stdout
    page = (out / "report.html").read_text()
    assert "exit status 130" in page and f"{got} of {planned} ticks recorded" in page
    assert "interrupted" in page


def test_monte_carlo_figure_gives_n_per_point_linear_axes_where_narrow_and_the_law(tmp_path: Path) -> None:
    """Points averaging different numbers of replicates say so; a bound from 1.04 to 1.16 m is drawn on
    a linear axis; the title names the law."""
    from sim import study, studyplots, sweep

    rows = []
    for delay, bounds in ((0.0, (1.04, 1.05, 1.06, 1.07, 1.08, 1.09)), (50.0, (1.10, 1.12, 1.14, 1.16, 9e9, 9e9))):
        for n, b in enumerate(bounds):
            diverged = b > 1e6  # two replicates of the second cell diverged: it averages 4, the first 6
            rows.append({"law": "sigma", "loss_pct": 0.0, "delay_ms": delay, "burst": 1.0, "sigma": 1.0,
                         "gamma_p": 0.05, "gamma_v": 0.05, "seed": n, "diverged": diverged,
                         **{m: (None if diverged else b) for m in sweep.MC_METRICS}})
    summary = study.summarise(rows, sweep.GROUP, sweep.MC_METRICS)
    paths = studyplots.study_figures(rows, summary, tmp_path, {"seeds": 6}, title="section4")
    svg = paths[0].with_suffix(".svg").read_text()
    assert "n=6" in svg and "n=4" in svg and "law sigma" in svg
    assert not studyplots.wide([1.04, 1.16]) and studyplots.wide([0.01, 1.0])


@pytest.mark.slow  # a small sweep and a browser
def test_a_sweep_writes_a_report_that_opens_in_chromium(tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    done = tether("sweep", "section4", "--loss", "0,30", "--delay", "0,100", "--laws", "sigma", "--duration", "2",
                  "--out", str(out))
    assert done.returncode == 0, done.stderr
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert pngs and all((out / p).with_suffix(".svg").exists() for p in pngs)
    dom = check_in_browser(out / "report.html", tmp_path, len(pngs))
    assert "<table>" in dom and "section4" in dom
    (out / "report.html").unlink()
    assert tether("report", str(out)).returncode == 0 and (out / "report.html").exists()
