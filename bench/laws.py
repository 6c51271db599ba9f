"""Three formation laws side by side on the same missions: Eq. 17 (``sigma``), Eq. 30
(``benchmark``) and Eq. 17 with integral action (``integral``, ``agent/laws/integral.py``).

    PYTHONPATH=. python bench/laws.py --out docs/results/laws          # runs, table, figures, sweep
    PYTHONPATH=. python bench/laws.py --out OUT --no-sweep                # the runs and figures only

Scenarios (each flown by the three laws, nothing else changed):

* ``section4``: Section 4 as shipped (``tether/missions/section4.toml``, 1000 s, sinusoidal d_i);
* ``section4-bias``: the same with a constant ``d_y = -g 0.12 / 1.12`` added on agent 1: a vehicle
  12 % heavier than the mass its thrust is computed for. With thrust ``m (u + g)`` on a vehicle of
  mass ``1.12 m``, ``p'' = (u + g) / 1.12 - g = u / 1.12 - 0.12 g / 1.12``: the constant term is
  -1.051 m/s^2; the 1/1.12 gain error on ``u`` is not modelled (the plant is a double integrator);
* ``exp2``: Experiment 2 as shipped (quadrotors, payload, each vehicle's mass share fed forward and
  an inner integrator);
* ``exp2-plain``: Experiment 2 with the payload only an unknown disturbance (no mass share, no inner
  integrator: :func:`sim.experiments.exp2_variants`'s "plain law").

The integral law takes the mission's Eq. 17 parameters unchanged and adds ``integral_limit =
4 m/s^2`` and ``ki`` chosen by :func:`design_ki` from the linearised loop at the initial gains
(never from these runs). Section 4's scenarios run on the reference simulator (compiled kernel),
Experiment 2's on the in-process engine (the payload world).

Per run: the steady-state error (mean ``||xi_i||`` over agents and the last 20 % of the run), the
worst agent's, the constant part (largest ``||mean_tail xi_i||``), the slot error (mean over the
tail of ``max_i ||p_i - h_i - p_leader||``), the peak ``||xi_i||`` and the control effort (RMS of
``||u_i||`` over the run and the agents). Written to ``OUT``: ``laws.json``, ``table.md``,
``xi-<scenario>.png``; with the sweep, ``missions/`` and ``sweep-eq17/``, ``sweep-integral/`` (two
``tether sweep`` runs over the one-way delay, on ``section4-bias``) and ``sweep.md``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import msgspec  # noqa: E402
import numpy as np  # noqa: E402

from sim import experiments, figures, lockstep, metrics, refsim  # noqa: E402
from sim.reproduce import with_law  # noqa: E402
from tether import mission as ms  # noqa: E402
from tether.runfile import Run  # noqa: E402

G = 9.81
"""[m/s^2], as plant/vehicle.py."""
MASS_ERROR = 0.12
"""The vehicle is this fraction heavier than modelled."""
BIAS = -G * MASS_ERROR / (1.0 + MASS_ERROR)
"""[m/s^2]: the constant acceleration a 12 % mass error leaves (module docstring)."""
INTEGRAL_LIMIT = 4.0
"""[m/s^2]: the integral law's ``integral_limit`` in every scenario."""
TAIL = 0.2
"""The steady state: this last fraction of a run."""
KI_GRID = tuple(float(x) for x in np.round(np.geomspace(0.02, 2.0, 41), 4))
LAWS = ("sigma", "benchmark", "integral")
SWEEP_DELAYS_MS = (0, 20, 50, 100, 200)
SWEEP_DURATION_S = 300.0


def l1_of(m: ms.Mission) -> np.ndarray:
    """``L1`` (N, N) of mission ``m``: ``kappa_i`` on the diagonal (the leader's edge included),
    ``-a_ij`` off it."""
    ids = m.agent_ids
    lap = np.zeros((len(ids), len(ids)))
    for e in m.edges:
        i, j = ids.index(e.dst), e.src
        lap[i, i] += e.weight
        if j in ids:
            lap[i, ids.index(j)] -= e.weight
    return lap


def abscissa(l1: np.ndarray, kp: float, kv: float, ki: float) -> float:
    """Largest real part [1/s] of the eigenvalues of the integral law's loop linearised at gains
    ``kp, kv`` (held) around a formation of double integrators: ``p' = v``,
    ``v' = -K^-1 (kp L1 p + kv L1 v + ki s)``, ``s' = L1 p``, ``K = diag(kappa)``."""
    n = len(l1)
    kinv = np.diag(1.0 / np.diag(l1))
    z, eye = np.zeros((n, n)), np.eye(n)
    a = np.block([[z, eye, z], [-kp * kinv @ l1, -kv * kinv @ l1, -ki * kinv], [l1, z, z]])
    return float(np.max(np.linalg.eigvals(a).real))


def design_ki(m: ms.Mission) -> float:
    """The integral gain of :data:`KI_GRID` that makes the linearised loop (:func:`abscissa`, at the
    mission's initial gains ``kp0, kv0``; their first axis) decay fastest."""
    kp = ms.per_axis(m.law.kp0, m.dim)[0]
    kv = ms.per_axis(m.law.kv0, m.dim)[0]
    l1 = l1_of(m)
    return min(KI_GRID, key=lambda ki: abscissa(l1, kp, kv, ki))


def integral_of(m: ms.Mission, ki: float) -> ms.Mission:
    """``m`` flown by the integral law: its Eq. 17 parameters, ``ki`` and :data:`INTEGRAL_LIMIT`."""
    law = m.law
    params = {"kp0": law.kp0, "kv0": law.kv0, "gamma_p": law.gamma_p, "gamma_v": law.gamma_v,
              "sigma": float(law.sigma or 0.0), "ki": ki, "integral_limit": INTEGRAL_LIMIT}
    new = msgspec.structs.replace(law, kind="custom", use="integral", sigma=None, params=params)
    return msgspec.structs.replace(m, law=new, name=f"{m.name}-integral")


def biased(m: ms.Mission, agent_id: int = 1) -> ms.Mission:
    """``m`` with :data:`BIAS` added on the last axis of agent ``agent_id``'s disturbance."""
    agents = []
    for a in m.agents:
        if a.id == agent_id:
            bias = ms.Constant(value=[0.0] * (m.dim - 1) + [BIAS])
            a = msgspec.structs.replace(a, disturbance=ms.DisturbanceSum(
                terms=[*ms.disturbance_terms(a.disturbance), bias]))
        agents.append(a)
    return msgspec.structs.replace(m, agents=agents, name=f"{m.name}-bias")


def scenarios() -> dict[str, ms.Mission]:
    """The four base missions (flown by Eq. 17 as the shipped ones are)."""
    s4 = ms.load(REPO / "tether" / "missions" / "section4.toml")
    e2 = ms.load(REPO / "tether" / "missions" / "exp2.toml")
    plain = experiments.exp2_variants(e2)["plain law (payload as a disturbance only)"]
    return {"section4": s4, "section4-bias": biased(s4), "exp2": e2,
            "exp2-plain": msgspec.structs.replace(plain, name="exp2-plain")}


def flown(m: ms.Mission, law: str, ki: float) -> ms.Mission:
    if law == "sigma":
        return m
    if law == "benchmark":
        return with_law(m, "benchmark")
    return integral_of(m, ki)


def figures_of_merit(m: ms.Mission, run: Run) -> dict[str, float]:
    """The table's columns for one run (module docstring)."""
    xn = metrics.xi_norm(run)
    tail = metrics.tail_slice(run, TAIL)
    offsets = np.array([a.offset for a in m.agents], dtype=float)
    slot = np.linalg.norm(run.p - offsets[None] - run.leader_p[:, None, :], axis=2)
    u = np.linalg.norm(run.u, axis=2)
    return {
        "steady_xi_m": float(np.mean(xn[tail])),
        "steady_xi_worst_m": float(np.max(np.mean(xn[tail], axis=0))),
        "constant_xi_m": float(np.max(np.linalg.norm(np.mean(run.xi[tail], axis=0), axis=1))),
        "steady_slot_m": float(np.mean(np.max(slot[tail], axis=1))),
        "peak_xi_m": float(np.nanmax(xn)),
        "effort_rms_mps2": float(np.sqrt(np.mean(u * u))),
        "diverged": bool(not np.all(np.isfinite(run.xi))),
    }


def simulate(m: ms.Mission) -> Run:
    if any(not isinstance(a.plant, ms.DoubleIntegrator) for a in m.agents) or m.payload is not None:
        return lockstep.simulate(m)
    return refsim.simulate(m, engine="auto")


def xi_figure(runs: dict[str, Run], title: str, path: Path) -> Path:
    """One column per law: ``||xi_i||`` per agent, linear (top) and logarithmic (bottom)."""
    fig, ax = plt.subplots(2, len(runs), figsize=(4.6 * len(runs), 6.0), sharex=True, sharey="row", squeeze=False)
    for c, (label, run) in enumerate(runs.items()):
        step = max(1, len(run.t) // 4000)
        xn = metrics.xi_norm(run)[::step]
        for i, aid in enumerate(run.agent_ids):
            for r in range(2):
                ax[r, c].plot(run.t[::step], xn[:, i], lw=0.7, color=figures.colour(i), label=f"agent {aid}")
        ax[0, c].set_title(label)
        ax[1, c].set_yscale("log")
        ax[1, c].set_xlabel("t [s]")
        for r in range(2):
            ax[r, c].grid(True, lw=0.3)
    ax[0, 0].set_ylabel(r"$\|\xi_i\|$ [m]")
    ax[1, 0].set_ylabel(r"$\|\xi_i\|$ [m] (log)")
    ax[0, -1].legend(fontsize=7, loc="upper right")
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def table(rows: dict[str, dict[str, dict[str, float]]], kis: dict[str, float]) -> list[str]:
    head = ("| scenario | law | steady ‖ξ‖ mean [m] | worst agent [m] | constant part [m] | slot error [m] | "
            "peak ‖ξ‖ [m] | effort RMS ‖u‖ [m/s²] |")
    out = [head, "|" + "---|" * 8]
    for sc, by_law in rows.items():
        for law, r in by_law.items():
            name = f"integral (ki = {kis[sc]:g})" if law == "integral" else law
            flag = " (diverged)" if r["diverged"] else ""
            out.append(f"| {sc} | {name}{flag} | {r['steady_xi_m']:.4g} | {r['steady_xi_worst_m']:.4g} | "
                       f"{r['constant_xi_m']:.3g} | {r['steady_slot_m']:.4g} | {r['peak_xi_m']:.4g} | "
                       f"{r['effort_rms_mps2']:.4g} |")
    return out


def sweep(out: Path, m: ms.Mission, ki: float) -> list[str]:
    """Two ``tether sweep`` runs over :data:`SWEEP_DELAYS_MS` on ``m``: Eq. 17 and Eq. 30 in one, the
    integral law (a law of one's own to the sweep) in the other; returns :func:`sweep_table`."""
    (out / "missions").mkdir(parents=True, exist_ok=True)
    eq17 = out / "missions" / f"{m.name}.toml"
    eq17.write_text(ms.dumps(m))
    integ = out / "missions" / f"{m.name}-integral.toml"
    integ.write_text(ms.dumps(integral_of(m, ki)))
    delays = ",".join(str(d) for d in SWEEP_DELAYS_MS)
    common = ["--loss", "0", "--delay", delays, "--duration", f"{SWEEP_DURATION_S:g}"]
    for path, laws, where in ((eq17, "sigma,benchmark", "sweep-eq17"), (integ, "custom", "sweep-integral")):
        cmd = [sys.executable, "-m", "cli", "sweep", str(path), "--laws", laws, *common, "--out", str(out / where)]
        print("$", " ".join(cmd[1:]), flush=True)
        subprocess.run(cmd, check=True, cwd=REPO)
    return sweep_table(out)


def sweep_table(out: Path) -> list[str]:
    """The markdown table of the two sweeps' ``sweep.csv`` under ``out``: per delay and law, the
    ultimate bound of ``xi`` from the recorded positions and, in brackets, from the samples the
    agents used."""
    cells: dict[tuple[str, int], dict[str, str]] = {}
    for where in ("sweep-eq17", "sweep-integral"):
        with open(out / where / "sweep.csv", newline="") as f:
            for row in csv.DictReader(f):
                law = "integral" if row["law"] == "custom" else row["law"]
                cells[(law, int(float(row["delay_ms"])))] = row
    lines = ["| one-way delay [ms] | " + " | ".join(LAWS) + " |", "|---|" + "---|" * len(LAWS)]
    for d in SWEEP_DELAYS_MS:
        vals = []
        for law in LAWS:
            row = cells[(law, d)]
            vals.append("diverged" if row["diverged"] == "True" else
                        f"{float(row['ultimate_bound_m']):.3g} ({float(row['ultimate_bound_seen_m']):.3g})")
        lines.append(f"| {d} | " + " | ".join(vals) + " |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="directory for laws.json, table.md and the figures")
    ap.add_argument("--no-sweep", action="store_true", help="skip the netem sweep")
    ap.add_argument("--only", default="", help="comma-separated scenarios to run (default all)")
    args = ap.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    bases = scenarios()
    if args.only:
        bases = {k: v for k, v in bases.items() if k in args.only.split(",")}
    rows: dict[str, dict[str, dict[str, float]]] = {}
    kis: dict[str, float] = {}
    for sc, base in bases.items():
        kis[sc] = design_ki(base)
        runs: dict[str, Run] = {}
        rows[sc] = {}
        for law in LAWS:
            m = flown(base, law, kis[sc])
            t0 = time.perf_counter()
            runs[law] = simulate(m)
            rows[sc][law] = figures_of_merit(m, runs[law])
            print(f"{sc:14s} {law:10s} {time.perf_counter() - t0:6.1f} s  {rows[sc][law]}", flush=True)
        xi_figure(runs, f"{sc}: ‖ξ_i‖ under the three laws", out / f"xi-{sc}.png")
    lines = table(rows, kis)
    print("\n".join(lines))
    (out / "laws.json").write_text(json.dumps({"rows": rows, "ki": kis, "integral_limit": INTEGRAL_LIMIT,
                                               "bias_mps2": BIAS, "tail": TAIL}, indent=1) + "\n")
    md = ["# Three laws, measured by bench/laws.py", "", *lines, ""]
    if not args.no_sweep:
        sw = sweep(out, biased(ms.load(REPO / "tether" / "missions" / "section4.toml")), kis.get("section4-bias")
                   or design_ki(ms.load(REPO / "tether" / "missions" / "section4.toml")))
        print("\n".join(sw))
        md += ["## Delay sweep (section4-bias, 300 s): ultimate bound of ‖ξ‖ [m] from the positions (as the agents saw it)",
               "", *sw, ""]
    (out / "table.md").write_text("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
