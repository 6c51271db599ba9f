"""Two sites: a ground-station router and a field router linked router-to-router, agents split
between them (deploy/hosts.py ``[[routers]]``, deploy/gen.py, deploy/rehearse.py ``--partition``).

* Fast: what ``tether deploy-gen`` writes for two routers (the field router dials the ground one
  with its own certificate, every other process dials its own site's router, both routers hold the
  same access rules and grant each other routing), and the bad two-router hosts files it refuses
  (a link to an unknown router, a loop, a host with no route to the leader's router): exit 2 naming
  the field and the fix.
* Root: a rehearsal of Section 4 on two sites (leader, recorder, agents 1 and 2 on the ground
  router; agents 3 and 4 on the field router), each router a machine of its own; the link between
  the two routers is cut for a few seconds mid-flight and healed. Agent 3, whose only input (agent 2)
  is across the cut, holds; agent 1 drops its edge from agent 4 and flies on; after the heal every
  agent flies again and the formation error comes back within a bound.

Namespaces ``tether-rh<pid>-...`` (as tests/test_rehearse.py), addresses 10.77.1.0/24 inside them only.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from deploy import gen, hosts
from tests.support import read
from tests.support import log_time
from tests.test_rehearse import RESTART_SAFETY, needs_namespaces, run_rehearsal
from tether import mission as ms
from tether.catalog import builtin_path
from tether.runfile import Run

REPO = Path(__file__).resolve().parents[1]
SECTION4 = builtin_path("section4")
TWO_SITES = """\
version = 1
config_dir = {config}
[[routers]]
name = "ground"
address = "10.77.1.1"
[[routers]]
name = "field"
address = "10.77.1.2"
connect = ["ground"]
[leader]
address = "10.77.1.1"
router = "ground"
[recorder]
address = "10.77.1.1"
out = {out}
[[agents]]
id = 1
address = "10.77.1.11"
[[agents]]
id = 2
address = "10.77.1.12"
router = "ground"
[[agents]]
id = 3
address = "10.77.1.13"
router = "field"
[[agents]]
id = 4
address = "10.77.1.14"
router = "field"
"""


def write_hosts(tmp: Path, text: str = TWO_SITES) -> tuple[Path, Path]:
    out = tmp / "deploy"
    path = tmp / "hosts.toml"
    path.write_text(text.format(config=json.dumps(str(out / "hosts" / "{host}")),
                                out=json.dumps(str(tmp / "recorder-out"))))
    return path, out


def profile(dep: gen.Deployment, name: str) -> dict:
    text = dep.config(name).read_text()
    return json.loads("\n".join(ln for ln in text.splitlines() if not ln.startswith("//")))


# =========================================================================== fast: generation
def test_two_sites_are_generated_router_to_router(tmp_path: Path) -> None:
    path, out = write_hosts(tmp_path)
    dep = gen.generate(SECTION4, out, hosts=path)
    assert dep.plan.host_names[:2] == ["router-ground", "router-field"]
    ground, field = profile(dep, "router-ground"), profile(dep, "router-field")
    assert ground["mode"] == field["mode"] == "router"
    assert ground["listen"]["endpoints"] == ["tls/10.77.1.1:7447"] and "connect" not in ground
    assert field["listen"]["endpoints"] == ["tls/10.77.1.2:7447"]
    assert field["connect"]["endpoints"] == ["tls/10.77.1.1:7447"]  # the link, dialled by the field router
    tls = field["transport"]["link"]["tls"]
    assert tls["enable_mtls"] and tls["verify_name_on_connect"] and tls["connect_certificate"].endswith(
        "router-field.crt")
    assert field["transport"]["link"]["protocols"] == ["tls"]
    # each router grants the other what the processes on its side may do (tests/test_router_links.py)
    subjects = {s["id"]: s["cert_common_names"] for s in ground["access_control"]["subjects"]}
    assert subjects["router-field"] == ["router-field.section4"] and "router-ground" not in subjects
    subjects = {s["id"]: s["cert_common_names"] for s in field["access_control"]["subjects"]}
    assert subjects["router-ground"] == ["router-ground.section4"] and "router-field" not in subjects
    assert "router" not in subjects
    # every process dials its own site's router, and only it
    dials = {n: profile(dep, n)["connect"]["endpoints"] for n in
             ("leader-5", "control-0", "recorder-0", "agent-1", "plant-1", "agent-2", "agent-3", "plant-3",
              "agent-4", "plant-4")}
    assert {n for n, d in dials.items() if d == ["tls/10.77.1.2:7447"]} == {"agent-3", "plant-3", "agent-4",
                                                                          "plant-4"}
    assert all(d in (["tls/10.77.1.1:7447"], ["tls/10.77.1.2:7447"]) for d in dials.values())
    units = sorted(p.name for p in (out / "hosts").glob("*/systemd/tether-router-*.service"))
    assert units == ["tether-router-field.service", "tether-router-ground.service"]
    unit = (out / "hosts" / "router-field" / "systemd" / "tether-router-field.service").read_text()
    assert f"--config {out}/hosts/router-field/router-field.json5" in unit
    assert not (out / "hosts" / "router-field" / "mission.toml").exists()
    assert "`router-field` → `router-ground`" in (out / "DEPLOY.md").read_text()


M = ms.load(SECTION4)
BAD_SITES = [
    (TWO_SITES.replace('connect = ["ground"]', 'connect = ["base"]'), "routers[1].connect[0]",
     "is 'base', not a router of this file; use one of 'ground', 'field'"),
    (TWO_SITES.replace('connect = ["ground"]', 'connect = ["field"]'), "routers[1].connect[0]",
     "this router itself: a loop"),
    (TWO_SITES.replace('name = "ground"\n', 'name = "ground"\nconnect = ["field"]\n'), "routers[1].connect[0]",
     "already linked (directly or through other routers): a loop"),
    (TWO_SITES.replace('connect = ["ground"]\n', ''), "agent 3.router",
     "has no route to the leader's router 'ground'"),
    (TWO_SITES.replace('id = 4\naddress = "10.77.1.14"\nrouter = "field"', 'id = 4\naddress = "10.77.1.14"\n'
                                                                         'router = "feild"'),
     "agent 4.router", "is 'feild', not a router of this file"),
    (TWO_SITES.replace('name = "field"', 'name = "Field site"'), "routers[1].name", "lower-case name"),
    (TWO_SITES.replace('name = "field"', 'name = "ground"').replace('"field"', '"ground"'), "routers[1].name",
     "already the name of routers[0]"),
    (TWO_SITES + '[router]\naddress = "10.77.1.1"\n', "routers", "together with [router]"),
    (TWO_SITES.replace('id = 2\naddress = "10.77.1.12"', 'id = 2\naddress = "tls/10.77.1.12"'), "agent 2.address",
     "no scheme, no port"),
    (TWO_SITES.replace('[[agents]]\nid = 4\naddress = "10.77.1.14"', '[[agents]]\nid = 4\nadress = "10.77.1.14"'),
     "agent 4.adress", "rename it to `address`"),
]


@pytest.mark.parametrize(("body", "field", "fix"), BAD_SITES, ids=[f"{b[1]}:{b[2][:24]}" for b in BAD_SITES])
def test_bad_two_site_hosts_files_name_the_field_and_the_fix(body: str, field: str, fix: str) -> None:
    text = body.format(config='"/etc/tether"', out='"/var/lib/tether/runs"')
    with pytest.raises(hosts.HostsError) as err:
        hosts.plan(M, hosts.loads(text, "h.toml"), "h.toml")
    problems = dict(err.value.problems)
    assert field in problems, err.value
    assert fix.lower() in problems[field].lower(), err.value


def test_tether_deploy_gen_exits_2_on_a_router_loop(tmp_path: Path) -> None:
    path, out = write_hosts(tmp_path, TWO_SITES.replace('name = "ground"\n', 'name = "ground"\nconnect = ["field"]\n'))
    done = subprocess.run([sys.executable, "-m", "cli", "deploy-gen", str(SECTION4), "--out", str(out), "--hosts",
                           str(path)], cwd=REPO, capture_output=True, text=True, timeout=120,
                          env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert done.returncode == 2, done.stderr
    assert "routers[1].connect[0]: links 'field' to 'ground'" in done.stderr and "a loop" in done.stderr
    assert not out.exists()


# =========================================================================== root: two sites flown, cut, healed
DURATION = 28.0
CUT_AT, CUT_FOR = 6.0, 5.0
"""The router-to-router link is cut at mission time CUT_AT [s] for CUT_FOR [s]."""
SEEN_WITHIN = 2.0 + 1.0 + 2.0
"""Cut to agent 3 holding [s]: the lease (2 s, the hosts file's default), neighbour_timeout (1 s),
and slack for two loaded cores."""
SETTLED = 6.0
"""After agent 3 flies again, the formation error is bounded from this long on [s] (the field
vehicles catch up a formation that moved on at up to max_accel)."""
BOUND = 3.0
"""Bound on ||xi|| [m] before the cut and from SETTLED after the heal (Section 4 flies at <= 1.6 m
under real-time noise)."""


@pytest.mark.slow  # a real-time rehearsal of 24 s on two sites with their link cut
def test_two_sites_fly_survive_a_partition_and_rejoin(tmp_path: Path) -> None:
    needs_namespaces()
    mission = tmp_path / "mission.toml"
    mission.write_text(SECTION4.read_text() + RESTART_SAFETY)
    path, out = write_hosts(tmp_path)
    gen.generate(mission, out, hosts=path)
    run_dir = tmp_path / "run"
    status, output = run_rehearsal(tmp_path / "rehearse.log", str(out), "--out", str(run_dir), "--duration",
                                   repr(DURATION), "--partition", f"router-ground:router-field@{CUT_AT:g}+{CUT_FOR:g}",
                                   timeout=140)
    assert status == 3, output[-4000:]  # the far side held: a failsafe fired, as tether run would say
    record = json.loads((run_dir / "rehearsal.json").read_text())
    spaces = {u: v["namespace"] for u, v in record["units"].items()}
    assert spaces["tether-router-ground"] == spaces["tether-leader-5"] != spaces["tether-router-field"]
    assert all(len(u["pids"]) == 1 for u in record["units"].values())  # nothing restarted
    (cut,) = record["partitions"]
    cut_wall, heal_wall = cut["cut_wall"], cut["heal_wall"]

    def modes(aid: int) -> list[tuple[float, str, str, str]]:
        text = read(run_dir / "logs" / f"tether-agent-{aid}.log")
        return [(log_time(ln), *m.groups()) for ln in text.splitlines() if ln[:4].isdigit()
                and (m := re.search(r"safety: t = [0-9.]+ s: (\w+) -> (\w+): (.*)", ln))]

    # the far side: agent 3 hears only agent 2, across the cut: it holds, and flies again after the heal
    m3 = modes(3)
    hold = next((e for e in m3 if e[0] >= cut_wall - 0.01 and e[2] == "HOLD"), None)
    assert hold is not None, m3
    back = next((e for e in m3 if e[0] >= hold[0] and e[1] == "HOLD" and e[2] == "FLYING"), None)
    assert back is not None, m3
    print(f"\nagent 3: HOLD {hold[0] - cut_wall:.2f} s after the cut ({hold[3]}), FLYING {back[0] - heal_wall:.2f} s "
          f"after the heal ({back[3]})")
    assert hold[0] - cut_wall <= SEEN_WITHIN
    assert not [e for e in m3 if e[2] in ("LAND", "ESTOP")]
    # the near side: agent 1 hears the leader on its own site: it flies on
    assert not [e for e in modes(1) if cut_wall <= e[0] <= heal_wall and e[2] != "FLYING"], modes(1)
    log1 = read(run_dir / "logs" / "tether-agent-1.log")
    assert re.search(r"agent/4|edge 4", log1), log1[-3000:]
    run = Run.load(run_dir)
    col = {int(a): i for i, a in enumerate(run.agent_ids)}
    epoch = record["epoch"]
    t_cut, t_heal = cut_wall - epoch, heal_wall - epoch
    norm = np.linalg.norm(run.xi, axis=-1)
    before = norm[(run.t > 3.0) & (run.t < t_cut)]
    t_back = back[0] - epoch  # the field side flies again: the routers relinked (their retry period: 1-4 s)
    after = norm[run.t >= t_back + SETTLED]
    around = norm[(run.t >= t_cut) & (run.t < t_back + SETTLED)]
    print(f"max ||xi|| before the cut {np.nanmax(before):.2f} m, from the cut to {SETTLED:g} s after agent 3 flies "
          + ", ".join(f"{a}: {np.nanmax(around[:, col[a]]):.2f} m" for a in (1, 2, 3, 4))
          + f", after {np.nanmax(after):.2f} m")
    assert np.nanmax(before) < BOUND and np.nanmax(after) < BOUND
    assert t_back + SETTLED < DURATION - 1.0
    assert np.isfinite(after).mean() > 0.8  # the field side's telemetry reaches the recorder again
    assert not [e for e in run.safety.events if e.dst >= 2], "a vehicle landed or stopped"
