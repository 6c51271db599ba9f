"""Figures and the report of a study with more axes than loss x delay: the law's sigma and rates
(``--sigma``, ``--gamma-p``, ``--gamma-v``) and Monte Carlo replicates (``--seeds``).

One figure, ``study.png`` (and its SVG): the ultimate bound of the true ``||xi||``, the gains'
convergence time and the peak gain against sigma when the study has several sigmas, else against
the delay; one line per combination of the other axes that vary; log axes only where the values
span more than a decade (:data:`WIDE`); the law named in the title. With replicates, each point is
the mean over the replicates that did not diverge, labelled with how many (``n=``), with its 95 %
Student-t confidence interval as error bars; the report's tables give mean, standard deviation and
interval.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

AXES = ("law", "loss_pct", "delay_ms", "burst", "sigma", "gamma_p", "gamma_v")
LABEL = {"law": "law", "loss_pct": "loss %", "delay_ms": "delay ms", "burst": "burst", "sigma": "σ",
         "gamma_p": "Γp", "gamma_v": "Γv"}
PANELS = (("ultimate_bound_m", r"ultimate bound of the true $\|\xi\|$ [m]", True),
          ("gain_convergence_s", "gain convergence time [s] (within 5 % of final)", False),
          ("peak_gain", r"peak gain max($K_p$, $K_v$)", False))


def _varying(rows: list[dict]) -> list[str]:
    return [a for a in AXES if len({r[a] for r in rows}) > 1]


def _value(row: dict, metric: str, summary: bool) -> tuple[float, float, float]:
    """(centre, lower, upper) of one metric in one cell: the mean and its interval, or the value."""
    if summary:
        m, lo, hi = row[f"{metric}_mean"], row[f"{metric}_ci_lo"], row[f"{metric}_ci_hi"]
    else:
        m = row.get(metric)
        m = math.nan if m is None or row.get("diverged") else m
        lo = hi = m
    f = (lambda x: math.nan if x is None else float(x))
    return f(m), f(lo), f(hi)


def study_figures(rows: list[dict], summary: list[dict] | None, out: Path, meta: dict, title: str = "") -> list[Path]:
    """Draw ``study.png`` (see the module docstring); returns its path."""
    cells = summary if summary is not None else rows
    vary = _varying(cells)
    x_axis = "sigma" if "sigma" in vary else ("delay_ms" if "delay_ms" in vary else (vary[0] if vary else "delay_ms"))
    series_axes = [a for a in vary if a != x_axis]
    groups: dict[tuple, list[dict]] = {}
    for r in cells:
        groups.setdefault(tuple(r[a] for a in series_axes), []).append(r)
    fig, ax = plt.subplots(1, len(PANELS), figsize=(5.2 * len(PANELS), 4.4), squeeze=False)
    for c, (metric, label, logy) in enumerate(PANELS):
        a = ax[0, c]
        shown: list[float] = []
        for key, members in groups.items():
            members = sorted(members, key=lambda r: r[x_axis])
            x = np.array([float(r[x_axis]) for r in members])
            v = np.array([_value(r, metric, summary is not None) for r in members])
            name = ", ".join(f"{LABEL[k]} {val:g}" if isinstance(val, float) else f"{val}"
                             for k, val in zip(series_axes, key)) or "cells"
            if summary is not None:
                err = np.vstack([v[:, 0] - v[:, 1], v[:, 2] - v[:, 0]])
                err = np.where(np.isfinite(err), err, 0.0)
                a.errorbar(x, v[:, 0], yerr=err, marker="o", capsize=3, label=name)
                for xi, yi, r in zip(x, v[:, 0], members):  # how many replicates this point averages
                    n = r.get(f"{metric}_n")
                    if n is not None and np.isfinite(yi):
                        a.annotate(f"n={int(n)}", (xi, yi), xytext=(4, 4), textcoords="offset points", fontsize=7)
            else:
                a.plot(x, v[:, 0], marker="o", label=name)
            shown.extend(float(y) for y in v[:, 1:].ravel() if np.isfinite(y) and y > 0)
        if x_axis == "sigma" and all(float(r["sigma"]) > 0 for r in cells) and wide([float(r["sigma"]) for r in cells]):
            a.set_xscale("log")
        if logy and wide(shown):
            a.set_yscale("log")
        a.set_xlabel(LABEL.get(x_axis, x_axis))
        a.set_title(label, fontsize=9)
        a.grid(True, which="both", alpha=0.3)
    ax[0, 0].legend(fontsize=7)
    ci = (f"; mean of the replicates that did not diverge (n per point, of {meta['seeds']}), bars: 95 % "
          "t-interval" if summary is not None else "")
    laws = sorted({str(r["law"]) for r in cells})
    fig.suptitle(f"{title}, law {', '.join(laws)}{ci}", fontsize=10)
    fig.tight_layout()
    path = out / "study.png"
    fig.savefig(path, dpi=110)
    fig.savefig(path.with_suffix(".svg"))
    plt.close(fig)
    return [path]


WIDE = 10.0
"""A log axis only where the values span more than this ratio; a narrow range reads better linear."""


def wide(values: list[float]) -> bool:
    """Whether positive ``values`` span more than :data:`WIDE` (max over min)."""
    pos = [v for v in values if v > 0 and math.isfinite(v)]
    return bool(pos) and max(pos) / min(pos) > WIDE


def _fmt(x: object) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x:.3g}" if isinstance(x, float) else str(x)


def report(rows: list[dict], summary: list[dict] | None, meta: dict, figures: list[Path]) -> str:
    """``sweep.md`` of such a study: one table row per cell (computed, not written)."""
    cells = summary if summary is not None else rows
    vary = _varying(cells) or ["law"]
    lines = [f"# Study of `{meta['mission']}`", "",
             f"{meta['engine']} lockstep engine, {meta['duration_s']:g} s at {meta['rate_hz']:g} Hz, mission seed "
             f"{meta['seed']}, {meta['cells']} cells"
             + (f", {meta['seeds']} Monte Carlo replicates per cell (new seed, start positions within "
                f"±{meta['p0_jitter_m']:g} m, random sinusoid phases); mean ± standard deviation "
                "[95 % Student-t interval of the mean] over the replicates that did not diverge"
                if summary is not None else "")
             + ". Definitions: docs/netem.md (Degradation studies) and docs/studies.md.", ""]
    lines += [f"![{p.stem}]({p.name})" for p in figures]
    metrics = [m for m, _, _ in PANELS]
    head = [LABEL[a] for a in vary] + ["ultimate bound [m]", "gain convergence [s]", "peak gain", "diverged"]
    lines += ["", "| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for r in cells:
        vals = []
        for m in metrics:
            if summary is not None:
                vals.append(f"{_fmt(r[f'{m}_mean'])} ± {_fmt(r[f'{m}_std'])} "
                            f"[{_fmt(r[f'{m}_ci_lo'])}, {_fmt(r[f'{m}_ci_hi'])}]")
            else:
                vals.append("✗" if r["diverged"] else _fmt(r.get(m)))
        div = f"{r['diverged']}/{r['replicates']}" if summary is not None else ("yes" if r["diverged"] else "no")
        lines.append("| " + " | ".join([_fmt(r[a]) for a in vary] + vals + [div]) + " |")
    return "\n".join(lines) + "\n"
