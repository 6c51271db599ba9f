"""Figures a paper can use: files written, and the properties that make them readable checked on
matplotlib's own objects (aspect, colours, labels, notes), not on pixels."""

from __future__ import annotations

from pathlib import Path

import matplotlib.colors as mcolors
import matplotlib.pyplot as plt
import numpy as np
import pytest

from sim import figures, refsim
from tether import catalog
from tether import mission as ms
from tether.runfile import Run


def simulated(name: str, duration: float) -> Run:
    path = catalog.builtin_path(name)
    m = ms.with_duration(ms.load(path), duration, str(path))
    run = refsim.simulate(m)
    run.meta.mission_text = path.read_text()
    return run


@pytest.fixture(scope="module")
def section4() -> Run:
    return simulated("section4", 40.0)


def rgb(c: object) -> tuple[float, ...]:
    return tuple(round(x, 3) for x in mcolors.to_rgb(c))  # type: ignore[arg-type]


def lines_by_label(ax: object) -> dict[str, tuple[float, ...]]:
    return {ln.get_label(): rgb(ln.get_color()) for ln in ax.get_lines()}  # type: ignore[attr-defined]


def test_run_panels_write_the_four_figures_each_with_its_svg(section4: Run, tmp_path: Path) -> None:
    paths = figures.run_panels(section4, tmp_path)
    assert [p.name for p in paths] == ["errors_gains.png", "velocities.png", "xy.png", "formation.png"]
    assert all(p.stat().st_size > 10_000 for p in paths)
    for p in paths:
        svg = p.with_suffix(".svg").read_text()
        assert svg.lstrip().startswith("<?xml") and "<svg" in svg and f"law {section4.meta.law}" in svg


def test_one_colour_per_agent_across_every_panel(section4: Run) -> None:
    want = {int(aid): rgb(figures.colour(i)) for i, aid in enumerate(section4.agent_ids)}
    fig = figures.comparison_figure({"sigma": section4})
    err, kp, kv = fig.axes[:3]
    assert {int(lab.split()[1]): c for lab, c in lines_by_label(err).items() if lab.startswith("agent")} == want
    for ax in (kp, kv):
        got = lines_by_label(ax)
        for aid, c in want.items():
            assert got[f"{aid}x"] == got[f"{aid}y"] == c  # the axes differ by line style, not colour
    plt.close(fig)
    fig = figures.velocities_figure(section4)
    for ax in fig.axes:
        got = lines_by_label(ax)
        assert all(got[f"agent {aid}"] == c for aid, c in want.items())
    plt.close(fig)
    fig = figures.xy_figure(section4)
    world, rel = fig.axes
    for ax in (world, rel):
        got = lines_by_label(ax)
        assert all(got[f"agent {aid}"] == c for aid, c in want.items())
    # the snapshot markers and the target slots carry the agent's colour too
    markers = [c for c in world.collections if len(c.get_offsets()) == len(want)]
    assert markers
    for coll in markers:
        colours = coll.get_facecolors() if coll.get_facecolors().size and coll.get_facecolors()[0][3] > 0 \
            else coll.get_edgecolors()
        assert [tuple(round(x, 3) for x in c[:3]) for c in colours] == list(want.values())
    plt.close(fig)


def test_gains_carry_their_units(section4: Run) -> None:
    fig = figures.comparison_figure({"sigma": section4})
    assert [ax.get_ylabel() for ax in fig.axes[1:3]] == ["$K_p$ [1/s²]", "$K_v$ [1/s]"]
    assert fig.axes[0].get_ylabel().endswith("[m]") and "own" in fig.axes[0].get_ylabel()
    plt.close(fig)


def test_errors_figure_shows_the_true_formation_error_beside_the_agents_own() -> None:
    """Eq. 8 from the positions and the tracking error, each labelled, above the agents' own
    ||xi_i||; the plotted true error is :func:`sim.metrics.formation_error`'s, computed here
    independently from the offsets and the graph."""
    section4 = simulated("section4", 15.0)  # short enough to be drawn sample by sample
    fig = figures.errors_figure(section4)
    labels = [ax.get_ylabel() for ax in fig.axes if ax.get_ylabel()]
    assert labels[0].startswith("true formation error") and "Eq. 8" in labels[0]
    assert labels[1].startswith("tracking error") and labels[2].startswith("agents' own")
    assert labels[3:] == ["$K_p$ [1/s²]", "$K_v$ [1/s]"]
    assert "law sigma" in fig.texts[0].get_text()
    true_ax = fig.axes[0]
    ln = next(ln for ln in true_ax.get_lines() if ln.get_label() == "agent 1")
    x, y = ln.get_data()
    # Eq. 8 summed edge by edge from the mission's graph, the leader's slot at h = 0
    from tether import graph

    m = ms.loads(section4.meta.mission_text or "")
    a = graph.topology(m).adjacency
    h = np.vstack([figures.mission_offsets(section4), np.zeros((1, 2))])
    e = np.concatenate([section4.p, section4.leader_p[:, None]], axis=1) - h[None]
    xi1 = sum(a[0, j] * (e[:, 0] - e[:, j]) for j in range(len(h)))
    want = np.linalg.norm(xi1, axis=1)
    k = np.searchsorted(section4.t, np.asarray(x, dtype=float))
    assert np.allclose(np.asarray(y, dtype=float), want[k], atol=1e-9)
    plt.close(fig)


def test_a_long_run_is_drawn_as_envelopes_with_its_ends_zoomed() -> None:
    run = simulated("section4", 300.0)
    fig = figures.errors_figure(run)
    grid = fig.axes[0].get_gridspec()
    assert (grid.nrows, grid.ncols) == (5, 3)
    first, whole, last = fig.axes[:3]
    assert first.get_xlim() == (0.0, figures.ZOOM) and last.get_xlim()[1] == pytest.approx(300.0)
    assert len(whole.collections) == len(run.agent_ids)  # one min/max band per agent
    assert all(len(ln.get_xdata()) <= figures.ENVELOPE for ln in whole.get_lines())
    plt.close(fig)


def test_event_labels_never_overprint() -> None:
    # 4 vehicles change mode within 0.1 s, another event later, one far: three labels, alternating
    times = [10.0, 10.02, 10.05, 10.1, 30.0, 36.0]
    got = figures.event_labels(times, span=100.0)
    assert [(t, text) for t, text, _ in got] == [(10.0, "1-4"), (30.0, "5"), (36.0, "6")]
    levels = [lvl for _, _, lvl in got]
    assert all(a != b for a, b in zip(levels, levels[1:]))  # neighbours on different levels
    # labels on the same level are further apart than a cluster
    same = [t for t, _, lvl in got if lvl == 0]
    assert all(b - a > figures.LABEL_GAP * 100.0 for a, b in zip(same, same[1:]))


def test_the_formation_is_drawn_to_scale_with_its_target_slots(section4: Run) -> None:
    fig = figures.xy_figure(section4)
    world, rel = fig.axes
    assert rel.get_aspect() == 1.0  # to scale: the diamond is a diamond
    # Section 4 spans hundreds of metres by a few: the world view says it is not to scale
    assert world.get_aspect() == "auto" and "not to scale" in world.get_title()
    labels = {ln.get_label() for ln in rel.get_lines()} | {c.get_label() for c in rel.collections}
    assert {"target formation", "target slots $h_i$"} <= labels
    slots = next(c for c in rel.collections if c.get_label() == "target slots $h_i$")
    offsets = figures.mission_offsets(section4)
    assert offsets is not None
    assert np.allclose(np.sort(slots.get_offsets(), axis=0), np.sort(offsets[:, :2], axis=0))
    target = next(ln for ln in rel.get_lines() if ln.get_label() == "target formation")
    ring = np.column_stack(target.get_data())
    assert len(ring) == len(offsets) + 1 and np.allclose(ring[0], ring[-1])  # a closed polygon
    edges = np.linalg.norm(np.diff(ring, axis=0), axis=1)
    assert np.allclose(edges, edges[0])  # around the diamond (not across it): four equal sides
    world_labels = {ln.get_label() for ln in world.get_lines()} | {c.get_label() for c in world.collections}
    assert {"target formation", "target slots", "formation"} <= world_labels
    plt.close(fig)


def test_a_compact_world_view_is_to_scale(tmp_path: Path) -> None:
    run = simulated("failsafe", 4.0)
    fig = figures.xy_figure(run)
    assert fig.axes[0].get_aspect() == 1.0 and "not to scale" not in fig.axes[0].get_title()
    plt.close(fig)
    fig = figures.snapshots_figure(run, (0.0, 2.0), three_d=True)
    ax = fig.axes[0]
    labels = {ln.get_label() for ln in ax.get_lines()} | {c.get_label() for c in ax.collections}
    assert {"formation", "target formation", "target slots"} <= labels
    plt.close(fig)
    assert figures.snapshots(run, (0.0, 2.0), tmp_path / "s.png").stat().st_size > 5_000


def test_curves_that_coincide_are_noted(section4: Run) -> None:
    run = section4
    kp = run.kp.copy()
    kp[:, 1] = kp[:, 0]  # agent 2's gains exactly agent 1's: the curves hide each other
    import dataclasses

    fig = figures.comparison_figure({"sigma": dataclasses.replace(run, kp=kp)})
    notes = [t.get_text() for t in fig.axes[1].texts]
    assert any(n.startswith("coincide: ") and "1x = 2x" in n and "1y = 2y" in n for n in notes), notes
    plt.close(fig)
    t = np.linspace(0, 1, 50)
    assert figures.coinciding([("a", t), ("b", t + 1e-9), ("c", t + 0.5)]) == [["a", "b"]]
    assert figures.coinciding([("a", t), ("b", t[::-1])]) == []


def test_the_relative_view_is_framed_on_the_vehicles_in_flight_and_marks_the_landed() -> None:
    """Agent 1 lands at 5 s and is left far behind (its position then 200 m off): the relative view
    keeps the formation's scale, and marks where agent 1 left its slot."""
    import dataclasses

    import msgspec

    from tether import wire

    run = simulated("failsafe", 10.0)
    k = int(np.searchsorted(run.t, 5.0))
    mode = run.safety.safety_mode.copy()
    mode[k:, 0] = wire.LANDED
    p = run.p.copy()
    p[k + 1:, 0, :2] = p[k, 0, :2] - 200.0
    landed = dataclasses.replace(run, p=p, safety=msgspec.structs.replace(run.safety, safety_mode=mode))
    fig = figures.xy_figure(landed)
    rel = fig.axes[1]
    (x0, x1), (y0, y1) = rel.get_xlim(), rel.get_ylim()
    assert x1 - x0 < 10.0 and y1 - y0 < 10.0  # the 1 m diamond, not 200 m of landed vehicle
    marks = [c for c in rel.collections if c.get_label().startswith("left its slot")]
    assert len(marks) == 1
    assert any(t.get_text().startswith(f"{int(run.agent_ids[0])} down at") for t in rel.texts)
    plt.close(fig)


def test_a_lost_vehicle_leaves_only_the_agents_that_hear_it_without_a_true_error() -> None:
    """failsafe: leader -> 1, 3; ring 1 -> 2 -> 3 -> 4 -> 1. Vehicle 2's position gone from 5 s: the
    true error of 2 and of 3 (which hears 2) is undefined after it, that of 1 and 4 is not."""
    import dataclasses

    from sim import metrics

    run = simulated("failsafe", 8.0)
    g = metrics.geometry(run)
    assert g is not None
    k = int(np.searchsorted(run.t, 5.0))
    p = run.p.copy()
    p[k:, 1] = np.nan
    cut = dataclasses.replace(run, p=p)
    true = metrics.true_xi_norm(cut, g)
    ids = [int(a) for a in run.agent_ids]
    assert np.all(np.isnan(true[k:, ids.index(2)])) and np.all(np.isnan(true[k:, ids.index(3)]))
    assert np.all(np.isfinite(true[:, ids.index(1)])) and np.all(np.isfinite(true[:, ids.index(4)]))
    np.testing.assert_allclose(true[:k], metrics.true_xi_norm(run, g)[:k], rtol=0, atol=1e-12)
    fig = figures.errors_figure(cut)
    assert any("no position of vehicle 2 after" in t.get_text() for t in fig.axes[0].texts)
    plt.close(fig)
