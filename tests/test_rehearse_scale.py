"""The deployment of a rehearsal at scale (deploy/rehearse.py): 16 agents on 8 companion computers,
two vehicles (agent and plant each) a host, router, leader and recorder on a ground station: 9
network namespaces, 36 units. Its flight is measured by ``bench/rehearse_scale.py`` (a ring mission
of 16 from ``bench/missions.py``, raised clear of the ground), not tested: on two cores it measures
the machine's load as much as tether (docs/deploy.md, Scale)."""

from __future__ import annotations

from pathlib import Path

from bench import rehearse_scale as scale
from deploy import rehearse

AGENTS = 16
PER_HOST = 2
RATE = 50.0
"""[Hz] The mission's rate (Exp. 1's gains: its lockstep run diverges at 20 Hz and dips metres at 25 Hz)."""
DURATION = 20.0
"""Mission time [s]."""


def test_the_scale_deployment_puts_two_vehicles_on_each_of_eight_hosts(tmp_path: Path) -> None:
    """The hosts file gives 8 companion computers of 2 vehicles each and a ground station; the
    rehearsal's plan makes one namespace of each machine and runs all 36 units."""
    _, deploy = scale.prepare(tmp_path, AGENTS, PER_HOST, RATE, DURATION)
    pl = rehearse.plan(deploy)
    assert len(pl.machines) == 9
    assert pl.hosts["agent-1"] == pl.hosts["agent-2"] == "10.77.0.11" != pl.hosts["agent-3"]
    assert pl.hosts["agent-16"] == "10.77.0.18" and pl.hosts["router"] == pl.hosts["recorder"] == "10.77.0.1"
    names = {u.name for u in pl.units}
    assert len(names) == 2 * AGENTS + 4 and {"tether-agent-16", "tether-plant-16", "tether-start"} <= names
