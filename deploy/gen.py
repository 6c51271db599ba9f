"""``tether deploy-gen MISSION --out DIR [--hosts hosts.toml] [--ca DIR]``: every host's files.

From a mission and a hosts file (``deploy/hosts.py``), writes::

    DIR/ca/ca.crt, ca.key          the deployment's CA (keep ca.key offline; it never goes to a host)
    DIR/acl.json5                  the access-control section every listener enforces, for review
    DIR/DEPLOY.md                  which directory goes to which host, and how to start the run
    DIR/hosts/<host>/              copy to that host's config_dir (default /etc/tether):
        mission.toml               the mission
        <process>.json5            one Zenoh configuration per process on the host
        tls/ca.crt, tls/<process>.crt, tls/<process>.key
        systemd/tether-<process>.service

Hosts: ``router`` (the Zenoh router, a Python session in router mode), ``leader`` (the virtual
leader and the operator's start command ``control-0``), ``recorder``, and one ``agent-<i>`` per
vehicle (agent i and its plant). Crazyflies have no companion computer: their plants are flown from
the radio host (``leader``, or ``radio`` when the hosts file names one), one unit
``tether-radio-<k>`` per dongle (``python -m cli.radio``), with their agents unless the hosts file
places them. Profiles: the router's (``mode: router``, listens), clients'
(``network = "client"``: connect to the router only) or peers' (``network = "peer"``: listen on
their host and connect to the router, which relays where there is no direct link). Every link is
TLS 1.3 with client certificates (mTLS); ``transport/link/protocols`` is ``["tls"]``, so no
process listens on or dials plain TCP; listeners enforce the access control of ``deploy/acl.py``.

Files are made as ``tether run`` makes its own (``tether/safefs.py``): ``--out`` owned by the user
and writable by nobody else, on a path others cannot redirect, or exit 2 before anything is
written; ``ca/`` and each ``tls/`` mode 0700, every ``*.key`` mode 0600 from its creation; each file
written under an exclusive temporary name and renamed over its name (with ``--force``, a link left
at a file's name is replaced, never followed); a directory's name that is a link is refused (exit 2).
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from deploy import acl, pki
from deploy.hosts import HostsError, Placement, Plan, Radio, control_character, load, plan
from tether import catalog
from tether import mission as ms
from tether import safefs
from tether import transport as tp

UNITS = {"router": "tether-router.service", "leader": "tether-leader.service", "control": "tether-start.service",
         "recorder": "tether-recorder.service", "agent": "tether-agent.service", "plant": "tether-plant.service",
         "radio": "tether-radio.service"}
"""Template of each role's systemd unit, in ``deploy/systemd/`` (``radio``: one per dongle, every
Crazyflie plant of it; the radio's USB device and cflib's cache directory)."""
OPENSSL_JOBS = 4
"""Hosts written at once (each certificate is one ``openssl`` process; ``bench/deploygen.py`` times
the whole command)."""
HARDENING = "hardening.conf"
"""The sandboxing every unit holds, in ``deploy/systemd/``: a template's ``@HARDENING@`` line."""


@dataclass
class Deployment:
    """What :func:`generate` wrote."""

    out: Path
    plan: Plan
    ca: pki.Ca
    files: dict[str, list[Path]] = field(default_factory=dict)
    """Files written per host directory."""

    def host_dir(self, host: str) -> Path:
        return self.out / "hosts" / host

    def config(self, name: str) -> Path:
        """The Zenoh configuration of process ``name`` (``router``, ``agent-3``, ...)."""
        p = next(p for p in self.plan.placements if p.name == name)
        return self.host_dir(p.host) / f"{name}.json5"


class GenerateError(ValueError):
    """The output directory cannot be written as asked; the message says why and what to do."""


# --------------------------------------------------------------------------- Zenoh profiles
def profile(p: Placement, pl: Plan, access: dict[str, Any]) -> dict[str, Any]:
    """The Zenoh configuration (as a dict, JSON5-ready) of the process placed at ``p``.

    Keys checked against zenoh 1.10's schema: ``mode``, ``listen/endpoints``, ``connect/endpoints``,
    ``connect/timeout_ms``, ``scouting/multicast/enabled``, ``scouting/gossip/{enabled,
    autoconnect_strategy}``, ``transport/link/protocols``, ``transport/link/tx/{lease, keep_alive}``,
    ``transport/link/tls/{root_ca_certificate, listen_certificate, listen_private_key,
    connect_certificate, connect_private_key, enable_mtls, verify_name_on_connect}``, ``access_control``.
    """
    h = pl.hosts
    tls_dir = f"{pl.config_dir(p.host)}/tls"
    tls: dict[str, Any] = {"root_ca_certificate": f"{tls_dir}/ca.crt", "enable_mtls": True,
                           "verify_name_on_connect": True}
    if p.listen is not None:
        tls |= {"listen_certificate": f"{tls_dir}/{p.name}.crt", "listen_private_key": f"{tls_dir}/{p.name}.key"}
    tls |= {"connect_certificate": f"{tls_dir}/{p.name}.crt", "connect_private_key": f"{tls_dir}/{p.name}.key"}
    conf: dict[str, Any] = {"mode": p.mode, "listen": {"endpoints": [p.listen] if p.listen else []}}
    if p.mode != "router":
        conf["connect"] = {"endpoints": pl.dials(p), "timeout_ms": round(h.connect_timeout * 1000)}
    elif pl.dials(p):
        # a router-to-router link: dialled with the router's own certificate, checked by the other
        # router's access control like any link; a router retries its connect endpoints for ever
        conf["connect"] = {"endpoints": pl.dials(p)}
    strategy = {"peer": {"to_router": "always", "to_peer": "greater-zid"}}
    conf["scouting"] = {"multicast": {"enabled": False},
                        "gossip": {"enabled": True, "autoconnect_strategy": strategy}}
    conf["transport"] = {"link": {"protocols": ["tls"], "tx": {"lease": round(h.lease * 1000), "keep_alive": 4},
                                  "tls": tls}}
    if p.mode == "router":
        conf["transport"]["link"]["tx"]["queue"] = {"size": dict(tp.ROUTER_TX_QUEUE)}
    if p.listen is not None:
        conf["access_control"] = access
    return conf


def _json5(header: list[str], body: dict[str, Any]) -> str:
    return "".join(f"// {line}\n" for line in header) + json.dumps(body, indent=2) + "\n"


# --------------------------------------------------------------------------- systemd units
_PLACEHOLDER = re.compile(r"@([A-Z_]+)@")
_BARE = re.compile(r"[A-Za-z0-9_./:=+,@-]+")
WORD_LISTS = ("ExecStart", "ReadWritePaths")
"""Directives whose value systemd splits into words (unquoting each): a filled word is quoted whole."""


def exec_word(value: str) -> str:
    """``value`` as one word of an ``ExecStart=`` command line (or another list of words) that systemd
    reads back as ``value`` (systemd.service(5), *Command lines*; systemd.syntax(7), *Quoting*):
    ``%`` doubled (specifiers are expanded inside quotes too) and ``$`` doubled (variables likewise);
    a word with anything but letters, digits and ``_./:=+,@-`` in double quotes, with ``\\`` and ``"``
    escaped inside them (so a space, a lone ``;`` or a quote stays inside the word). A control
    character cannot be written in a unit and raises :class:`GenerateError`. Pure."""
    if (bad := control_character(value)) is not None:
        raise GenerateError(f"{value!r} holds a control character ({bad}), which no unit file can carry")
    text = value.replace("%", "%%").replace("$", "$$")
    if _BARE.fullmatch(value):
        return text
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def template_text(role: str) -> str:
    """The unit template of ``role`` (a key of :data:`UNITS`), its ``@HARDENING@`` line replaced by
    :data:`HARDENING`'s lines."""
    folder = resources.files("deploy") / "systemd"
    return (folder / UNITS[role]).read_text().replace("@HARDENING@\n", (folder / HARDENING).read_text())


def unit(role: str, values: dict[str, str | list[str]]) -> str:
    """The role's unit template with every ``@NAME@`` filled from ``values``; a placeholder without
    a value is an error (a template and the generator out of step). A list value is several words
    of a command line: it may only stand alone as a word of ``ExecStart=`` or ``ReadWritePaths=``,
    and each of its words is written as one (:func:`exec_word`).

    Values come from a checked :class:`~deploy.hosts.Plan` (no control character, paths absolute and
    normalised: :func:`deploy.hosts.path_problem`) and are written so that systemd reads them back
    unchanged: a word of ``ExecStart=`` or ``ReadWritePaths=`` that holds a placeholder is quoted
    whole (:func:`exec_word`); elsewhere ``%`` is doubled. The result has the template's lines, no
    more (checked): no value can add a directive."""
    template = template_text(role)
    missing = sorted({m for m in _PLACEHOLDER.findall(template) if m not in values})
    if missing:
        raise GenerateError(f"template {UNITS[role]} has placeholders the generator does not fill: {missing}")
    for name, value in values.items():
        for v in value if isinstance(value, list) else [value]:
            if (bad := control_character(v)) is not None:
                raise GenerateError(f"{name} = {v!r} holds a control character ({bad}); no unit is written")

    def one(name: str) -> str:
        value = values[name]
        if isinstance(value, list):
            raise GenerateError(f"template {UNITS[role]}: @{name}@ is several words; it may only stand alone as a "
                                f"word of {' or '.join(WORD_LISTS)}")
        return value

    def fill(text: str, escape: bool = True) -> str:
        return _PLACEHOLDER.sub(lambda mt: one(mt.group(1)).replace("%", "%%") if escape else one(mt.group(1)), text)

    def words(w: str) -> list[str]:
        whole = _PLACEHOLDER.fullmatch(w)
        if whole is not None and isinstance(values[whole.group(1)], list):
            return [exec_word(v) for v in values[whole.group(1)]]
        return [exec_word(fill(w, escape=False)) if _PLACEHOLDER.search(w) else w]

    lines = []
    for line in template.splitlines():
        key, sep, rest = line.partition("=")
        if sep and key in WORD_LISTS:
            line = key + "=" + " ".join(x for w in rest.split(" ") for x in words(w))
        elif line.startswith("#"):
            line = fill(line, escape=False)  # a comment: no specifiers
        else:
            line = fill(line)
        lines.append(line)
    text = "\n".join(lines) + "\n"
    if text.count("\n") != template.count("\n") + (not template.endswith("\n")):
        raise GenerateError(f"unit {UNITS[role]}: a value changed the number of lines")
    return text


def unit_name(p: Placement, pl: Plan) -> str:
    """The unit that runs process ``p``: a Crazyflie's plant runs in its dongle's radio unit."""
    if p.role == "control":
        return "tether-start.service"
    radio = pl.radio_of(p)
    return f"tether-{p.name if radio is None else radio.name}.service"


def command_words(role: str, values: dict[str, str]) -> list[str]:
    """The words of the ``ExecStart=`` line of ``role``'s unit template, each placeholder filled with
    its value as it is (the arguments the process gets, not a unit's quoted line)."""
    line = next(ln for ln in template_text(role).splitlines() if ln.startswith("ExecStart="))
    return [_PLACEHOLDER.sub(lambda mt: values[mt.group(1)], w) for w in line.partition("=")[2].split(" ")]


def radio_words(r: Radio, pl: Plan) -> list[str]:
    """The arguments of ``python -m cli.radio`` for radio host ``r``: each vehicle's ``tether plant``
    options after a ``--``, read from the plant unit's own template (``tether-plant.service``) filled
    for it, as its own unit would have run it (its identity, its configuration)."""
    out: list[str] = []
    for aid in r.agents:
        words = command_words("plant", {"TETHER": pl.hosts.tether, "CONFIG_DIR": pl.config_dir(r.host),
                                        "ID": str(aid), "NS": pl.ns, "NODE": f"plant-{aid}"})
        out += ["--", *words[words.index("plant") + 1:]]
    return out


# --------------------------------------------------------------------------- generate
def generate(mission: str | Path, out: str | Path, hosts: str | Path | None = None, ca: str | Path | None = None,
             force: bool = False) -> Deployment:
    """Write every host's configuration for ``mission`` into ``out`` (see the module docstring).

    ``mission``: a mission file or a shipped mission's name. ``hosts``: a hosts file (``None``:
    placeholder host names, client network). ``ca``: a directory with an existing ``ca.crt`` and
    ``ca.key`` to sign with (certificate rotation); ``None`` creates a new CA in ``out/ca``.
    ``force``: write into a non-empty ``out`` (files are overwritten, none is deleted; a CA already
    in ``out/ca`` is never replaced: pass it as ``ca``).

    ``out`` is checked before anything is written (:func:`tether.safefs.out_problem`: this user's,
    writable by nobody else, on a path others cannot redirect); everything under it is made through
    :mod:`tether.safefs`, following no link (:func:`_write`).

    Raises :class:`~tether.mission.MissionError`, :class:`~deploy.hosts.HostsError`,
    :class:`~deploy.pki.PkiError` or :class:`GenerateError`, each naming the field or file at fault.
    Blocks while openssl makes the keys (tens of milliseconds per process).
    """
    mission_path = catalog.resolve(str(mission))
    m = ms.load(mission_path)
    hosts_file = load(hosts) if hosts is not None else None
    pl = plan(m, hosts_file, source=str(hosts) if hosts is not None else "<default hosts>")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise GenerateError(f"--out {out} is a file; give a directory")
    if (unsafe := safefs.out_problem(out)) is not None:
        raise GenerateError(f"--out: {unsafe}")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise GenerateError(f"--out {out} is not empty; give a new directory, or --force to overwrite the files "
                            "written there (with --ca to keep its CA)")
    if ca is None and (out / "ca" / "ca.key").exists():
        raise GenerateError(f"--out {out} already holds a CA ({out / 'ca'}); pass --ca {out / 'ca'} to sign with it "
                            "(a new CA would orphan every certificate already on the hosts), or choose a new --out")
    given = (Path(ca), pki.load_ca(Path(ca))) if ca is not None else None
    try:  # every file under --out is made through its real path, following no link (tether/safefs.py)
        real = safefs.make_out(out)
        with safefs.Dir.open(real) as top:
            return _write(top, mission_path, m, pl, given)
    except OSError as exc:
        from tether.node import os_error

        raise GenerateError(f"--out {out}: {os_error(exc)}") from None


def _write(top: safefs.Dir, mission_path: Path, m: ms.Mission, pl: Plan,
           given: tuple[Path, pki.Ca] | None) -> Deployment:
    """Write the deployment into ``top`` (``--out``, checked and opened), signed by ``given`` (the
    ``--ca`` directory and its CA) or by a new CA in ``ca/``: files replaced through an
    exclusive temporary name (a link at a name is replaced, never followed), keys mode 0600 from
    their creation in mode-0700 directories (``ca/``, each host's ``tls/``); a directory name that
    is a link, or another user's, is :class:`~tether.safefs.UnsafePath`. Blocks for openssl."""
    if given is None:
        with top.sub("ca", private=True) as cadir:
            authority = pki.make_ca(cadir, f"tether {pl.ns} CA", pl.hosts.cert_days)
    else:
        ca_dir, authority = given
        if ca_dir.resolve() != (top.path / "ca").resolve():
            with top.sub("ca") as cadir:  # for reference; the key stays where it is
                cadir.replace("ca.crt", authority.cert.read_bytes())
    ca_cert = authority.cert.read_bytes()

    grants = acl.grants(m, pl.ns, routers=tuple(r.name for r in pl.routers))
    access = acl.access_control(grants, pl.ns)
    links = link_grants(pl, grants)
    router_access = {r: acl.access_control([g for g in grants if g.name not in links] + gs, pl.ns)
                     for r, gs in links.items()}
    top.replace("acl.json5", _json5(
        [f"access_control of deployment {pl.ns!r} (mission {m.name!r}), as every listener's profile holds it.",
         "Identities are certificate CNs <process>.<ns>; see DEPLOY.md for what each may do."], access).encode())

    dep = Deployment(top.path, pl, authority)
    mission_text = mission_path.read_bytes()
    for host in pl.host_names:
        dep.files[host] = []

    def write_host(hosts_dir: safefs.Dir, host: str) -> None:
        with hosts_dir.sub(host) as hdir, hdir.sub("tls", private=True) as tls, hdir.sub("systemd") as sd:
            written = dep.files[host]
            written.append(tls.replace("ca.crt", ca_cert))
            if any(p.role != "router" for p in pl.on(host)):
                written.append(hdir.replace("mission.toml", mission_text))
            common: dict[str, str | list[str]] = {"HOST": host, "NS": pl.ns, "USER": pl.hosts.user,
                                                  "CONFIG_DIR": pl.config_dir(host), "PYTHON": pl.hosts.python}
            for p in pl.on(host):
                addresses = list(dict.fromkeys(a for a in (p.address, _bind_of(p)) if a))
                cert, key = pki.issue_one_step(authority, tls, p.name, p.common_name(pl.ns), addresses,
                                               pl.hosts.cert_days)
                conf = hdir.replace(f"{p.name}.json5", _json5(
                    [f"Zenoh configuration of {p.name} (CN {p.common_name(pl.ns)}) on host {host!r}, "
                     f"deployment {pl.ns!r}; written by tether deploy-gen.",
                     f"mode {p.mode}" + (f", listens on {p.listen}" if p.listen else "")
                     + (f", connects to {', '.join(pl.dials(p))}" if pl.dials(p) else "")],
                    profile(p, pl, router_access.get(p.name, access))).encode())
                written += [cert, key, conf]
                if pl.radio_of(p) is None:
                    written.append(sd.replace(unit_name(p, pl), unit(p.role, {
                        **common, "ID": str(p.node_id), "NODE": p.name, "TETHER": pl.hosts.tether,
                        "OUT": pl.hosts.recorder.out if pl.hosts.recorder is not None else "/var/lib/tether/runs",
                    }).encode()))
            for r in pl.radios:
                if r.host == host:
                    written.append(sd.replace(f"tether-{r.name}.service", unit("radio", {
                        **common, "RADIO": r.name, "DONGLE": r.dongle, "IDS": ", ".join(map(str, r.agents)),
                        "VEHICLES": radio_words(r, pl)}).encode()))

    with top.sub("hosts") as hosts_dir, ThreadPoolExecutor(max_workers=OPENSSL_JOBS) as pool:
        # openssl runs in processes of its own: hosts are written side by side, each in its own directory
        for done in [pool.submit(write_host, hosts_dir, host) for host in pl.host_names]:
            done.result()
    top.replace("DEPLOY.md", guide(dep, m, grants, links).encode())
    return dep


def link_grants(pl: Plan, grants: list[acl.Grant]) -> dict[str, list[acl.Grant]]:
    """Per router of a several-site deployment, the grants of its neighbour routers on their links
    (:func:`acl.link_grant`: what the processes on the neighbour's side may do); empty for one router.
    A router that is not a neighbour gets no grant there: it has no link to open."""
    if len(pl.routers) < 2:
        return {}
    by_name = {g.name: g for g in grants}
    return {r.name: [acl.link_grant(n, [by_name[q.name] for q in pl.behind(r.name, n)]) for n in pl.neighbours(r.name)]
            for r in pl.routers}


def _bind_of(p: Placement) -> str | None:
    if p.listen is None:
        return None
    host = p.listen.removeprefix("tls/").rsplit(":", 1)[0].strip("[]")
    return None if host in ("0.0.0.0", "::") else host  # a wildcard bind names no host


def guide(dep: Deployment, m: ms.Mission, grants: list[acl.Grant],
          links: dict[str, list[acl.Grant]] | None = None) -> str:
    """The generated DEPLOY.md: hosts, files, commands, and what the access control allows."""
    pl = dep.plan
    q = shlex.quote  # the guide's commands are for a shell
    lines = [f"# Deployment of mission `{m.name}` (namespace `{pl.ns}`)", "",
             f"Written by `tether deploy-gen`. Network: **{pl.hosts.network}**; every link is TLS 1.3 with client "
             f"certificates (mTLS) signed by `ca/ca.crt`; certificates expire on "
             f"{pki.expiry(dep.host_dir(pl.router.host) / 'tls' / f'{pl.router.name}.crt')}. "
             "Keep `ca/ca.key` offline: it is not needed on any host. The guide is `docs/deploy.md`.", "",
             "| host dir | address | processes | listens on | services |", "|---|---|---|---|---|"]
    for host in pl.host_names:
        ps = pl.on(host)
        listens = ", ".join(p.listen for p in ps if p.listen) or "–"
        units = dict.fromkeys(unit_name(p, pl) for p in ps)
        lines.append(f"| `hosts/{host}/` → `{pl.config_dir(host)}` | {ps[0].address} | "
                     f"{', '.join(p.name for p in ps)} | {listens} | {', '.join(units)} |")
    if pl.radios:
        lines += ["", "## Radios", "",
                  "A Crazyflie has no companion computer: every Crazyflie's plant is flown from the radio host "
                  f"(`hosts/{pl.radios[0].host}/`), one process per dongle (`python -m cli.radio`), each vehicle still "
                  "a plant of its own (its identity, keys, watchdog and dead-man; docs/lab.md).", "",
                  "| unit | dongle | plants |", "|---|---|---|",
                  *(f"| `tether-{r.name}.service` | `{r.dongle}` | {', '.join(f'plant-{a}' for a in r.agents)} |"
                    for r in pl.radios), "",
                  "On that host the service user needs the radio: add it to group `plugdev` and install the udev rule "
                  "of docs/deploy.md (Hardened units). A `sim://` dongle is software Crazyflies on that host "
                  "(`udp://` URIs): start them there before the run (docs/cfsim.md; `tether rehearse --sitl` does)."]
    if pl.links():
        lines += ["", "Router-to-router links (each dialled by the first, TLS with the same mTLS): "
                  + ", ".join(f"`{a}` → `{b}`" for a, b in pl.links()) + ". On each, a router may say and hear "
                  "only what the processes on its side may (the tables below, per router)."]
    lines += ["", "## Install", "",
              "On each host: copy `hosts/<host>/` to the directory above (owned by root, readable by user "
              f"`{pl.hosts.user}`; the `*.key` files mode 0600 and owned by `{pl.hosts.user}`), install tether "
              f"so that `{pl.hosts.tether}` and `{pl.hosts.python}` exist, then",
              "", "```sh", f"sudo cp {shlex.quote(pl.config_dir('<host>'))}/systemd/*.service /etc/systemd/system/",
              "sudo systemctl daemon-reload", "```", "", "## Run", "",
              "1. router host" + ("s" if len(pl.routers) > 1 else "") + ": "
              + ", ".join(f"`sudo systemctl enable --now tether-{r.name}`" for r in pl.routers),
              "2. every other host: `sudo systemctl start tether-<process>` for each of its services "
              "(each waits for the start)",
              f"3. leader host: `sudo systemctl start tether-start` (or `{q(pl.hosts.python)} -m deploy.start --mission "
              f"{q(pl.config_dir('leader') + '/mission.toml')} --ns {pl.ns} "
              f"--zenoh-config {q(pl.config_dir('leader') + '/control-0.json5')}`): "
              "waits for every process's liveliness token, then announces tick 0 three seconds ahead",
              f"4. the recorder writes `{pl.hosts.recorder.out if pl.hosts.recorder else '/var/lib/tether/runs'}/run.npz` "
              "on its host; every process exits 0 after the last tick",
              f"5. to stop the swarm, on the leader host: `{q(pl.hosts.tether)} land --ns {pl.ns} --zenoh-config "
              f"{q(pl.config_dir('leader') + '/control-0.json5')}` (every vehicle lands), or `{q(pl.hosts.tether)} estop ...` "
              "(every motor off at once); only this identity may publish that order", "",
              "## What each identity may do (access control, default deny)", "",
              acl.describe([g for g in grants if not links or g.name not in links]), "",
              *(line for r, gs in (links or {}).items()
                for line in (f"At `{r}`, over its router-to-router links:", "", acl.describe(gs), "")),
              "Every identity may also be told of other processes' subscriptions in the namespace (its "
              "publishers need them to send) and of liveliness interest; nothing else (no queries, no deletes, "
              "no other key) passes a listener.", ""]
    return "\n".join(lines)


# --------------------------------------------------------------------------- command line
def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``deploy-gen`` options, for ``tether deploy-gen`` and ``python -m deploy.gen``."""
    p.add_argument("mission", help="mission file, or the name of a shipped mission")
    p.add_argument("--out", required=True, help="output directory (new, or use --force)")
    p.add_argument("--hosts", default=None, help="hosts file (TOML, docs/deploy.md); default: placeholder "
                                                 "host names tether-router, tether-agent-<i>, ... and a client star")
    p.add_argument("--ca", default=None, help="directory with an existing ca.crt and ca.key to sign with "
                                              "(certificate rotation); default: a new CA in OUT/ca")
    p.add_argument("--force", action="store_true", help="write into a non-empty --out (overwrites, deletes nothing)")


def run_args(args: argparse.Namespace) -> int:
    """Run ``deploy-gen`` from parsed arguments; prints errors and returns the exit status
    (0 written, 2 bad input: mission, hosts file, CA or output directory)."""
    try:
        dep = generate(args.mission, args.out, hosts=args.hosts, ca=args.ca, force=args.force)
    except (ms.MissionError, HostsError, pki.PkiError, GenerateError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for host in dep.plan.host_names:
        print(f"hosts/{host}/ -> {dep.plan.config_dir(host)} ({', '.join(p.name for p in dep.plan.on(host))})")
    print(f"wrote {dep.out} (read {dep.out / 'DEPLOY.md'})")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="tether deploy-gen", description=__doc__.splitlines()[0])
    add_arguments(p)
    return run_args(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
