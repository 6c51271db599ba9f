"""How ``tether deploy-gen`` and its access rules scale with the number of vehicles N.

    python bench/deploygen.py [--sizes 16,64,256,1024] [--avoid both|on|off] [--sites 1|2]

For each N (and with and without ``[safety.avoid]``, collision avoidance, whose agents hear every
other vehicle): a mission of N double integrators on a chain (the leader -> 1 -> 2 -> ... -> N, so
each agent has one in-neighbour), a hosts file with one companion computer per vehicle (addresses
10.x.y.z; with ``--sites 2`` the second half of the vehicles on a field router), and
``deploy.gen.generate`` into a temporary directory. Prints one row per case:

* ``generate [s]``: the whole command (mission and hosts checks, 2 N + 4 certificates through
  openssl, every file); ``rules [s]``: of it, the access rules alone (``acl.grants`` and
  ``acl.access_control``, pure);
* the router's ``access_control`` section: its size [kB], its rules and the key expressions they
  list, and the largest single grant (key expressions);
* ``keys declared``: the subscriptions the agents' own code declares (what the router must hold and
  route: with avoidance N (N - 1));
* ``router open [s]``: a Zenoh router session opened with the generated router configuration (on
  a free loopback port), the time Zenoh takes to parse and build those rules.

Figures are wall-clock times on whatever the machine is doing; the counts are exact.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import zenoh  # noqa: E402

from deploy import acl, gen  # noqa: E402
from deploy.hosts import plan  # noqa: E402
from tether import mission as ms  # noqa: E402
from tether import transport as tp  # noqa: E402


def mission_text(n: int, avoid: bool) -> str:
    """N double integrators on a chain behind the leader (id N + 1), 2D, offsets on a grid."""
    lead = n + 1
    edges = [f"{{ from = {lead}, to = 1 }}"] + [f"{{ from = {i}, to = {i + 1} }}" for i in range(1, n)]
    agents = "".join(f"[[agents]]\nid = {i}\np0 = [{(i - 1) % 32 * 3.0}, {(i - 1) // 32 * 3.0}]\n"
                     f"offset = [{(i - 1) % 32 * 3.0}, {(i - 1) // 32 * 3.0}]\n" for i in range(1, n + 1))
    return (f'version = 1\nname = "scale{n}"\ndim = 2\nrate = 50.0\nduration = 1.0\n'
            f"edges = [{', '.join(edges)}]\n"
            '[law]\nkind = "sigma"\nkp0 = 1.5\nkv0 = 1.2\ngamma_p = 0.1\ngamma_v = 0.05\nsigma = 0.1\n'
            f"[leader]\nid = {lead}\np0 = [0.0, 0.0]\n"
            + ("[safety.avoid]\nradius = 0.3\nsensing = 2.0\n" if avoid else "") + agents)


def hosts_text(n: int, sites: int, config_dir: Path) -> str:
    routers = ('[[routers]]\nname = "ground"\naddress = "10.0.0.1"\n[[routers]]\nname = "field"\n'
               'address = "10.0.0.2"\nconnect = ["ground"]\n') if sites == 2 else '[router]\naddress = "10.0.0.1"\n'
    out = f'version = 1\nconfig_dir = {json.dumps(str(config_dir))}\n{routers}[leader]\naddress = "10.0.0.1"\n[recorder]\naddress = "10.0.0.1"\n'
    for i in range(1, n + 1):
        field = sites == 2 and i > n // 2
        out += (f'[[agents]]\nid = {i}\naddress = "10.{1 + i // 65536}.{i // 256 % 256}.{i % 256}"\n'
                + (f'router = "{"field" if field else "ground"}"\n' if sites == 2 else ""))
    return out


def case(n: int, avoid: bool, sites: int, tmp: Path) -> dict[str, float | int]:
    mission, hosts = tmp / "mission.toml", tmp / "hosts.toml"
    mission.write_text(mission_text(n, avoid))
    hosts.write_text(hosts_text(n, sites, tmp / "out" / "hosts" / "{host}"))
    m = ms.load(mission)
    t0 = time.perf_counter()
    grants = acl.grants(m, m.name, routers=("router-ground", "router-field") if sites == 2 else ("router",))
    acl.access_control(grants, m.name)
    t_rules = time.perf_counter() - t0
    t0 = time.perf_counter()
    dep = gen.generate(mission, tmp / "out", hosts=hosts)
    t_gen = time.perf_counter() - t0
    router = dep.plan.routers[0].name
    config_path = dep.config(router)
    profile = json.loads("".join(ln for ln in config_path.read_text().splitlines(True) if not ln.startswith("//")))
    section = profile["access_control"]
    size = len(json.dumps(section))
    keys = sum(len(r["key_exprs"]) for r in section["rules"])
    largest = max(sum(len(r["key_exprs"]) for r in section["rules"] if r["id"] in p["rules"])
                  for p in section["policies"])
    declared = sum(len(ms.in_neighbours(m, a)) + len(ms.nearby_vehicles(m, a)) for a in m.agent_ids)
    config = tp.zenoh_config(tp.ZenohSettings(config_file=str(config_path)))
    config.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{tp.free_tcp_port()}"]))
    config.insert_json5("connect/endpoints", "[]")
    t0 = time.perf_counter()
    with zenoh.open(config):
        t_open = time.perf_counter() - t0
    plan(m, None)  # the placeholder plan, checked too (no timing: it is part of generate above)
    return {"generate": t_gen, "rules": t_rules, "kB": size / 1000, "n_rules": len(section["rules"]), "keys": keys,
            "largest": largest, "declared": declared, "open": t_open, "files": sum(len(v) for v in dep.files.values())}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="16,64,256,1024", help="numbers of vehicles, comma-separated")
    p.add_argument("--avoid", choices=("both", "on", "off"), default="both", help="[safety.avoid] in the mission")
    p.add_argument("--sites", type=int, choices=(1, 2), default=1, help="one router, or a ground and a field router")
    args = p.parse_args(argv)
    sizes = [int(x) for x in args.sizes.split(",")]
    avoids = {"both": (False, True), "on": (True,), "off": (False,)}[args.avoid]
    print("| N | avoidance | generate [s] | rules [s] | router section [kB] | rules | key expressions | largest grant "
          "| keys declared by agents | router open [s] |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for n in sizes:
        for avoid in avoids:
            with tempfile.TemporaryDirectory(prefix="tether-deploygen-") as tmp:
                r = case(n, avoid, args.sites, Path(tmp))
            print(f"| {n} | {'on' if avoid else 'off'} | {r['generate']:.1f} | {r['rules']:.3f} | {r['kB']:.0f} | "
                  f"{r['n_rules']} | {r['keys']} | {r['largest']} | {r['declared']} | {r['open']:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
