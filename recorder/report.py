"""A run's ``report.html``: one self-contained page a lab attaches to its log book.

Pure page building: :func:`run_page` turns a :class:`~tether.runfile.Run`, its metrics and its
figures (PNG bytes, drawn by the caller) into HTML text; :func:`study_page` does the same for a
study from its Markdown report. The page needs no network: inline CSS, figures as ``data:`` images,
the timeline as inline SVG, and one inline script that only records on the page whether every
figure decoded (``data-figures``) and any script error (``data-errors``), for a headless browser
to read. Nothing here reads a file or the clock.
"""

from __future__ import annotations

import base64
import html
import math
import re
from collections.abc import Mapping, Sequence

import msgspec
import numpy as np

from tether.runfile import NO_SAMPLE, Run

CSS = """
body{font:14px/1.45 system-ui,sans-serif;margin:0 auto;max-width:1180px;padding:0 18px 40px;color:#222}
h1{font-size:22px;margin:18px 0 4px}h2{font-size:17px;margin:26px 0 6px;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:6px 0;font-size:13px}td,th{border:1px solid #ccc;padding:2px 7px;
text-align:left;vertical-align:top}th{background:#f2f2f2}td.n{text-align:right;font-variant-numeric:tabular-nums}
.status{padding:8px 12px;border-radius:4px;font-weight:600;margin:8px 0}.ok{background:#e5f5e5}
.warn{background:#fff4d6}.bad{background:#fde2e2}figure{margin:10px 0}figure img{max-width:100%;
border:1px solid #ddd}figcaption{font-size:12px;color:#555}pre{background:#f7f7f7;padding:8px;overflow:auto;
font-size:12px}.muted{color:#666;font-size:12px}svg text{font:11px system-ui,sans-serif}
"""

PROBE = """
<script>
window.addEventListener('error', function (e) {
  var b = document.body; b.dataset.errors = (b.dataset.errors || '') + (e.message || 'error') + ';';
}, true);
window.addEventListener('load', function () {
  var imgs = document.querySelectorAll('img'), ok = 0;
  imgs.forEach(function (i) { if (i.complete && i.naturalWidth > 0) ok++; });
  document.body.dataset.figures = ok + '/' + imgs.length;
});
</script>
"""
"""Records on the page whether its figures decoded and any script error (for a headless check)."""

MODE_COLOURS = {"FLYING": "#8fd18f", "HOLD": "#f2c94c", "LAND": "#f2994a", "LANDED": "#9e9e9e",
                "ESTOP": "#d64545"}


def esc(x: object) -> str:
    return html.escape(str(x), quote=True)


def fmt(x: object) -> str:
    """A value for a table cell: numbers to 4 significant figures, no value as "–"."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, float):
        return f"{x:.4g}"
    return str(x)


def table(head: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """An HTML table, numbers right-aligned."""
    def cell(v: object) -> str:
        num = isinstance(v, (int, float)) and not isinstance(v, bool)
        return f"<td class='n'>{esc(fmt(v))}</td>" if num else f"<td>{esc(fmt(v))}</td>"

    out = ["<table><tr>" + "".join(f"<th>{esc(h)}</th>" for h in head) + "</tr>"]
    out += ["<tr>" + "".join(cell(v) for v in r) + "</tr>" for r in rows]
    return "".join(out) + "</table>"


def figure(name: str, png: bytes, caption: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return (f"<figure><img alt='{esc(name)}' src='data:image/png;base64,{data}'>"
            f"<figcaption>{esc(caption)}</figcaption></figure>")


METRIC_TEXT = {
    "duration_s": "mission time over which every agent's telemetry was recorded [s]",
    "formation_error_bound_m": "true formation error ‖ξ_i‖ (Eq. 8, from the positions), max over the last 10 % [m]",
    "formation_error_max_m": "true formation error, max over the run [m]",
    "formation_settling_time_s": "time from which the true formation error stays within 0.1 m [s]",
    "tracking_error_m": "distance of a vehicle from its slot p_leader + h_i, max over the last 10 % [m]",
    "tracking_error_max_m": "distance from the slot, max over the run [m]",
    "ultimate_bound_xi_m": "agents' own ‖ξ_i‖ (from the data they had), max over the last 10 % [m]",
    "settling_time_s": "time from which the agents' own max ‖ξ_i‖ stays within settle_band_m [s]",
    "settle_band_m": "the band of settling_time_s: 1.1 × ultimate_bound_xi_m [m]",
    "max_xi_m": "agents' own ‖ξ_i‖, max over the run [m]",
    "peak_kp": "largest Kp [1/s²]", "peak_kv": "largest Kv [1/s]",
    "final_kp_mean": "mean Kp at the end [1/s²]", "final_kv_mean": "mean Kv at the end [1/s]",
    "kp_growth_per_s": "slope of the mean Kp over the second half [1/s³]",
    "kv_growth_per_s": "slope of the mean Kv over the second half [1/s²]",
    "diverged": "a non-finite value or ‖ξ‖ > 1e6 m",
}
"""What each metric of ``metrics.json`` is, in the page's words (``docs/metrics.md``)."""


def _mission_section(run: Run) -> str:
    from tether import graph
    from tether import mission as ms

    text = run.meta.mission_text
    if not text:
        return "<p class='muted'>The run file holds no mission text.</p>"
    try:
        m = ms.loads(text)
    except ms.SchemaError as exc:
        return f"<p class='muted'>The mission text could not be read ({esc(exc)}).</p><pre>{esc(text)}</pre>"
    topo = graph.topology(m)  # its edges, not its adjacency matrix (N^2: a 10 000-agent chain)
    ids = [ag.id for ag in m.agents]
    heard: list[list[str]] = [[] for _ in ids]
    kappa = [0.0] * len(ids)
    for src, dst, w in zip(topo.src.tolist(), topo.dst.tolist(), topo.weight.tolist()):
        heard[dst].append(("leader" if src == len(ids) else str(ids[src])) + (f" ({w:g})" if w != 1 else ""))
        kappa[dst] += w
    rows = [[ag.id, ", ".join(f"{x:g}" for x in ag.offset), kappa[i], ", ".join(heard[i])]
            for i, ag in enumerate(m.agents)]
    law = msgspec.to_builtins(m.law)
    law_rows = [[k, ", ".join(f"{x:g}" for x in v) if isinstance(v, list) else fmt(v)] for k, v in law.items()]
    parts = [f"<p>{len(ids)} agents in {m.dim}D, {m.rate:g} Hz, {m.duration:g} s in its file; plants: "
             f"{esc(', '.join(sorted({type(ag.plant).__name__ for ag in m.agents})))}; network: {'emulated ([netem])' if m.netem is not None else 'ideal'}"
             f"{'; payload' if m.payload is not None else ''}.</p>",
             "<h3>Law</h3>", table(["parameter", "value"], law_rows),
             "<h3>Agents and graph</h3>", table(["agent", "offset h_i [m]", "κ_i", "hears (weight)"], rows),
             f"<details><summary>mission file</summary><pre>{esc(text)}</pre></details>"]
    return "".join(parts)


def _timeline(run: Run, worst: np.ndarray | None, worst_label: str, marks: Sequence[tuple[float, str]]) -> str:
    """An inline SVG on one time axis: the worst error over time, each vehicle's supervisor mode as a
    coloured lane, the safety events (ticks on their vehicle's lane) and the launcher's and faults'
    ``marks`` (dashed lines, numbered)."""
    t = run.t
    ok = np.isfinite(t)
    if not ok.any():
        return "<p class='muted'>No tick recorded.</p>"
    t0, t1 = float(t[ok][0]), float(t[ok][-1])
    span = max(t1 - t0, 1e-9)
    w, left, right = 1100, 70, 10
    lane, top = 16, 110
    n = len(run.agent_ids)
    h = top + lane * n + 34
    plot_w = w - left - right

    def x(tt: float) -> float:
        return left + plot_w * (tt - t0) / span

    out = [f"<svg xmlns='http://www.w3.org/2000/svg' width='{w}' height='{h}' viewBox='0 0 {w} {h}' "
           "role='img' aria-label='timeline'>"]
    if worst is not None and np.isfinite(worst).any():
        step = max(1, len(t) // 1500)
        tt, yy = t[::step], worst[::step]
        top_y = float(np.nanmax(yy)) or 1.0
        pieces: list[list[str]] = [[]]
        for a, b in zip(tt, yy):  # a gap where nothing was recorded, never a line across it
            if np.isfinite(a) and np.isfinite(b):
                pieces[-1].append(f"{x(float(a)):.1f},{100 - 90 * float(b) / top_y:.1f}")
            elif pieces[-1]:
                pieces.append([])
        out += [f"<polyline fill='none' stroke='#1f77b4' stroke-width='1' points='{' '.join(pc)}'/>"
                for pc in pieces if pc]
        out.append(f"<text x='{left - 4}' y='14' text-anchor='end'>{top_y:.3g} m</text>"
                   f"<text x='{left - 4}' y='100' text-anchor='end'>0</text>"
                   f"<text x='{left + 4}' y='12'>{esc(worst_label)}</text>")
    modes = run.meta.modes
    mode = run.safety.safety_mode
    for i, aid in enumerate(run.agent_ids):
        y = top + lane * i
        out.append(f"<text x='{left - 4}' y='{y + 12}' text-anchor='end'>agent {int(aid)}</text>")
        col = mode[:, i]
        start = 0
        for k in range(1, len(col) + 1):
            if k == len(col) or col[k] != col[start]:
                code = int(col[start])
                name = modes[code] if 0 <= code < len(modes) else ("no sample" if code == NO_SAMPLE else str(code))
                if np.isfinite(t[start]) and np.isfinite(t[k - 1]):
                    x0, x1 = x(float(t[start])), x(float(t[k - 1]))
                    out.append(f"<rect x='{x0:.1f}' y='{y + 2}' width='{max(x1 - x0, 0.8):.1f}' height='{lane - 4}' "
                               f"fill='{MODE_COLOURS.get(name, '#ffffff')}'><title>agent {int(aid)}: {esc(name)} "
                               f"from {float(t[start]):.2f} s</title></rect>")
                start = k
    for e in run.safety.events:
        if e.vehicle in [int(a) for a in run.agent_ids]:
            i = [int(a) for a in run.agent_ids].index(e.vehicle)
            y = top + lane * i
            out.append(f"<line x1='{x(e.t):.1f}' x2='{x(e.t):.1f}' y1='{y}' y2='{y + lane}' stroke='#b00' "
                       f"stroke-width='2'><title>{esc(e.reason)}</title></line>")
    for n_mark, (tm, text) in enumerate(marks, 1):
        if math.isfinite(tm):
            out.append(f"<line x1='{x(tm):.1f}' x2='{x(tm):.1f}' y1='0' y2='{top + lane * n}' stroke='#6a3d9a' "
                       f"stroke-dasharray='4 3'><title>{esc(text)}</title></line>"
                       f"<text x='{x(tm) + 2:.1f}' y='{top - 4 - 10 * (n_mark % 2)}' fill='#6a3d9a'>"
                       f"F{n_mark}</text>")
    ya = top + lane * n + 14
    out.append(f"<line x1='{left}' x2='{w - right}' y1='{ya - 10}' y2='{ya - 10}' stroke='#444'/>")
    for k in range(6):
        tk = t0 + span * k / 5
        out.append(f"<text x='{x(tk):.1f}' y='{ya + 6}' text-anchor='middle'>{tk:.4g} s</text>")
    legend = " ".join(f"<tspan fill='{c}'>■</tspan> {m}" for m, c in MODE_COLOURS.items())
    out.append(f"<text x='{left}' y='{h - 2}'>{legend}</text></svg>")
    return "".join(out)


def _links_section(run: Run) -> str:
    lk = run.links
    if lk is None:
        return "<p class='muted'>This run file holds no per-link statistics (the in-process engines do not "\
               "emulate links).</p>"
    rows = []

    def last(a: np.ndarray | None, i: int, d: int) -> float:
        if a is None:
            return math.nan
        if a.ndim == 2:
            return float(a[i, d])
        col = a[:, i, d]
        col = col[np.isfinite(col)]
        return float(col[-1]) if col.size else math.nan

    for i, aid in enumerate(run.agent_ids):
        for d, src in enumerate(lk.src[i]):
            if int(src) == 0:
                continue
            age = lk.age[:, i, d]
            age = age[np.isfinite(age)]
            frm = "leader" if int(src) > max(int(a) for a in run.agent_ids) else f"agent {int(src)}"
            rows.append([f"{frm} → agent {int(aid)}", last(lk.received, i, d), last(lk.used, i, d),
                         last(lk.stale, i, d), last(lk.duplicates, i, d), last(lk.reordered, i, d),
                         last(lk.corrupt, i, d), last(lk.delivery, i, d),
                         float(np.median(age)) * 1e3 if age.size else math.nan,
                         float(np.percentile(age, 99)) * 1e3 if age.size else math.nan])
    return table(["link", "received", "used (ticks)", "stale", "duplicates", "reordered", "corrupt",
                  "delivery", "age median [ms]", "age p99 [ms]"], rows)


def run_page(run: Run, metrics: Mapping[str, object], figures: Sequence[tuple[str, bytes, str]], *,
             status: tuple[int, str] | None = None, launcher_events: Sequence[Mapping[str, object]] = (),
             faults: Sequence[Mapping[str, object]] = (), worst: np.ndarray | None = None,
             worst_label: str = "", notes: Sequence[str] = ()) -> str:
    """The report of one run, as HTML text. ``metrics``: ``metrics.json``'s; ``figures``: ``(name,
    PNG bytes, caption)``; ``status``: the exit status and its meaning (a launched run);
    ``launcher_events`` and ``faults``: ``events.json`` and ``faults.json`` rows (``t`` [s] where
    known); ``worst``: ``(T,)`` the error drawn over the timeline, named ``worst_label``; ``notes``:
    warnings the command gave (what it did not compute, a stall it saw)."""
    meta = run.meta
    mode = run.safety.safety_mode
    every = int(np.all(mode != NO_SAMPLE, axis=1).sum()) if mode.size else len(run.t)
    some = int(np.any(mode != NO_SAMPLE, axis=1).sum()) if mode.size else len(run.t)
    held = f"{some} of {len(run.t)} ticks recorded" + (f" ({every} with every agent's telemetry)"
                                                       if every != some else "")
    parts = [f"<h1>{esc(meta.mission)}: law {esc(meta.law)}</h1>",
             f"<p class='muted'>{esc(meta.source)}, {meta.rate:g} Hz, seed {meta.seed}; {held}"
             + (f"; namespace {esc(meta.namespace)}" if meta.namespace else "")
             + (f"; {esc(meta.recovered)}" if meta.recovered else "") + "</p>"]
    if status is not None:
        code, meaning = status
        cls = "ok" if code == 0 else ("warn" if code in (3, 5) else "bad")
        parts.append(f"<div class='status {cls}' id='status'>exit status {code}: {esc(meaning)}</div>")
    parts += [f"<p class='status warn'>{esc(n)}</p>" for n in notes]
    order = [k for k in METRIC_TEXT if k in metrics] + [k for k in metrics if k not in METRIC_TEXT]
    rows = [[k, metrics[k], METRIC_TEXT.get(k, "")] for k in order]
    parts += ["<h2 id='metrics'>Metrics</h2>", table(["metric", "value", "what it is"], rows)]
    marks = [_mark(f) for f in faults] + [_mark(e) for e in launcher_events]
    marks = [(tm, f"F{n}: {text}") for n, (tm, text) in enumerate(marks, 1)]
    parts += ["<h2 id='timeline'>Errors, modes, events and faults on one time axis</h2>",
              _timeline(run, worst, worst_label, marks)]
    ev_rows = [[f"{e.t:.3f}", e.vehicle, _mode(run, e.src), _mode(run, e.dst), e.reason]
               for e in sorted(run.safety.events, key=lambda e: e.t)]
    parts += ["<h3>Safety events (the vehicles' supervisors)</h3>",
              table(["t [s]", "vehicle", "from", "to", "why"], ev_rows) if ev_rows else "<p>None.</p>"]
    if marks:
        parts += ["<h3>Faults and launcher events</h3>",
                  table(["", "t [s]", "what"], [[f"F{n}", f"{tm:.3f}" if math.isfinite(tm) else "before tick 0",
                                                text.split(": ", 1)[1]] for n, (tm, text) in enumerate(marks, 1)])]
    parts += ["<h2 id='figures'>Figures</h2>"] + [figure(n, png, cap) for n, png, cap in figures]
    parts += ["<h2 id='links'>Links</h2>", _links_section(run)]
    parts += ["<h2 id='mission'>Mission</h2>", _mission_section(run)]
    return _page(f"{meta.mission}: law {meta.law}", "".join(parts))


def _mark(row: Mapping[str, object]) -> tuple[float, str]:
    """A fault (``faults.json``) or a launcher event (``events.json``) as ``(t, words)``."""
    def num(v: object) -> float:
        return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else math.nan

    if "fault" in row:
        fired = num(row.get("fired"))
        when = f"fired at {fired:.3f} s" if math.isfinite(fired) else "never fired"
        return (fired if math.isfinite(fired) else num(row.get("at"))), f"fault {row['fault']} ({when})"
    return num(row.get("t")), f"{row.get('who', '?')} {row.get('what', '')}: {row.get('why', '')}"


def _mode(run: Run, code: int) -> str:
    modes = run.meta.modes
    return modes[code] if 0 <= code < len(modes) else str(code)


def _page(title: str, body: str) -> str:
    return (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{esc(title)}</title>"
            f"<style>{CSS}</style>{PROBE}</head><body>{body}</body></html>\n")


IMAGE = re.compile(r"^!\[([^\]]*)\]\(([^)]+)\)$")


def study_page(markdown: str, images: Mapping[str, bytes]) -> str:
    """A study's report as HTML from its Markdown report (``sweep.md``): headings, paragraphs,
    tables, and its images (``![name](file.png)``) inlined from ``images`` (file name to PNG bytes)."""
    out: list[str] = []
    rows: list[list[str]] = []
    heading = "study"

    def flush() -> None:
        if rows:
            body = [r for r in rows[1:] if not all(set(c.strip()) <= {"-", ":"} for c in r)]
            out.append(table(rows[0], body))
            rows.clear()

    for line in markdown.splitlines():
        s = line.strip()
        if s.startswith("|"):
            rows.append([c.strip().strip("`") for c in s.strip("|").split("|")])
            continue
        flush()
        if not s:
            continue
        if s.startswith("#"):
            level = min(len(s) - len(s.lstrip("#")), 3)
            text = s.lstrip("#").strip().replace("`", "")
            heading = text if level == 1 else heading
            out.append(f"<h{level}>{esc(text)}</h{level}>")
        elif (img := IMAGE.match(s)) and img.group(2) in images:
            out.append(figure(img.group(1), images[img.group(2)], img.group(2)))
        else:
            out.append(f"<p>{esc(s.replace('`', ''))}</p>")
    flush()
    return _page(heading, "".join(out))
