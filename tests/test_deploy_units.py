"""The generated systemd units: every hosts-file field that reaches a unit or a command line is
refused with the fix or written so that systemd reads it back unchanged; the units' hardening.

* Every field (``tether``, ``python``, ``config_dir``, ``recorder.out``, ``user``, ``ns``, the
  addresses) gets every character class: control characters (newline, CR, tab, NUL, DEL, C1, the
  Unicode line separator, a bidirectional override), spaces, quotes, a backslash, ``$``, ``%``
  specifiers, a lone ``;``, non-ASCII letters, and for paths relative, ``..``, ``.``, ``//`` and a
  trailing ``/``. Each is either refused (``tether deploy-gen`` exits 2 naming the field and the
  fix, and writes nothing) or accepted, and then every unit keeps its template's directives (no
  injected line) and its words read back, by an independent reading of systemd.syntax(7), by
  ``tether rehearse``'s parser and, for a program's path, by ``systemd-analyze verify`` itself,
  as the value given. A router's name (two sites) with any of these classes is refused.
* Every generated unit of a simulated and of a Crazyflie deployment is rated "OK" (exposure at most
  3.0) by ``systemd-analyze security --offline=yes`` (skipped where it is not installed; each rating
  printed), keeping the control loop's real-time policy, and for a Crazyflie plant its USB devices,
  group ``plugdev`` and a cache directory of its own, which cflib's TOC cache uses.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from deploy import gen, hosts
from deploy.rehearse import parse_unit
from tests.test_deploy import MISSION
from tether import mission as ms

SYSTEMD_ANALYZE = shutil.which("systemd-analyze")

BASE: dict[str, object] = {
    "version": 1, "config_dir": "/srv/t/{host}", "tether": "/opt/t/bin/tether", "python": "/opt/t/bin/python",
    "user": "tether",
    "router": {"address": "10.0.0.1"}, "leader": {"address": "10.0.0.1"},
    "recorder": {"address": "10.0.0.1", "out": "/var/lib/t/runs"},
    "agents": [{"id": i, "address": f"10.0.0.1{i}"} for i in (1, 2, 3)],
}

PATHS = {"tether": "/opt/t{}/bin/tether", "python": "/opt/t{}/bin/python", "config_dir": "/srv/t{}/{{host}}",
         "recorder.out": "/var/lib/t{}/runs"}
"""Path fields: ``{}`` is where a character class goes."""
NAMES = {"user": "tether{}", "ns": "trio{}", "router.address": "router{}", "router.bind": "10.0.0.1{}",
         "leader.address": "ground{}", "agent 2.address": "uav2{}"}

CLASSES = {
    "newline": "\nExecStartPre=/bin/sh -c id", "cr": "a\rb", "tab": "a\tb", "nul": "a\x00b", "del": "a\x7fb",
    "c1": "a\x85b", "line-separator": "a\u2028b", "bidi-override": "a\u202eb",
    "space": " with space", "double-quote": 'a"b', "single-quote": "a'b", "backslash": "a\\b",
    "dollar": "$HOME", "specifier": "%n", "percent-percent": "%%", "semicolon": " ; b", "non-ascii": "-müß雪",
}
SHAPES = {"relative": "opt/t/bin/x", "dotdot": "/opt/t/../bin/x", "dot": "/opt/./t/x", "double-slash": "/opt//t/x",
          "trailing-slash": "/opt/t/x/"}
ACCEPTED_IN_PATHS = {"space", "specifier", "percent-percent", "semicolon", "non-ascii"}
"""Written quoted; every other class is refused in a path (and every class in a name or address)."""

CASES = ([(f, PATHS[f].format(v), c in ACCEPTED_IN_PATHS) for f in PATHS for c, v in CLASSES.items()]
         + [(f, v, False) for f in PATHS for v in SHAPES.values()]
         + [(f, NAMES[f].format(v), False) for f in NAMES for v in CLASSES.values()])
IDS = ([f"{f}:{c}" for f in PATHS for c in CLASSES] + [f"{f}:{s}" for f in PATHS for s in SHAPES]
       + [f"{f}:{c}" for f in NAMES for c in CLASSES])


def hosts_toml(field: str, value: str) -> str:
    """The base hosts file with ``field`` set to ``value`` (TOML written from JSON strings, which TOML reads)."""
    doc = json.loads(json.dumps(BASE))
    if field.startswith("agent 2."):
        doc["agents"][1][field.split(".")[1]] = value
    elif "." in field:
        table, key = field.split(".")
        doc[table][key] = value
    else:
        doc[field] = value
    lines = []
    for key, v in doc.items():
        if not isinstance(v, (dict, list)):
            lines.append(f"{key} = {json.dumps(v)}")
    for key, v in doc.items():
        for table in ([v] if isinstance(v, dict) else v if isinstance(v, list) else []):
            lines.append(f"[{key}]" if isinstance(v, dict) else f"[[{key}]]")
            lines += [f"{k} = {json.dumps(x)}" for k, x in table.items()]
    return "\n".join(lines) + "\n"


def systemd_words(line: str) -> list[str]:
    """A command line split as systemd.syntax(7) says (written from the manual, not from the generator):
    words at unquoted whitespace, double or single quotes around a word's parts, a backslash escaping the
    next character (C escapes are not used here); then ``%%`` is ``%`` and ``$$`` is ``$`` in each word,
    and any other specifier or variable is an error (the generator must never leave one)."""
    words: list[str] = []
    cur: list[str] = []
    started, quote, i = False, "", 0
    while i < len(line):
        c = line[i]
        if c == "\\":
            assert i + 1 < len(line), line
            cur.append(line[i + 1])
            started, i = True, i + 2
            continue
        if quote:
            if c == quote:
                quote = ""
            else:
                cur.append(c)
        elif c in " \t":
            if started:
                words.append("".join(cur))
                cur, started = [], False
        elif c in "\"'":
            quote, started = c, True
        else:
            cur.append(c)
            started = True
        i += 1
    assert not quote, f"unbalanced quote in {line!r}"
    if started:
        words.append("".join(cur))
    out = []
    for w in words:
        assert not re.search(r"%[^%]", w.replace("%%", "")), f"a specifier left in {w!r}"
        assert not re.search(r"\$[^$]", w.replace("$$", "")), f"a variable left in {w!r}"
        out.append(w.replace("%%", "%").replace("$$", "$"))
    return out


def directives(text: str) -> list[str]:
    return [ln.split("=", 1)[0] for ln in text.splitlines() if ln.strip() and not ln.startswith(("#", "["))]


def systemd_reads_program(path: str, scratch: Path) -> str:
    """The program path ``systemd-analyze verify`` reads from ``ExecStart=`` written with
    :func:`gen.exec_word` (it names it when the file does not exist)."""
    unit = scratch / "probe.service"
    unit.write_text(f"[Service]\nExecStart={gen.exec_word(path)} --x\n")
    done = subprocess.run([SYSTEMD_ANALYZE or "systemd-analyze", "verify", str(unit)], capture_output=True,
                          text=True, timeout=60)
    found = re.search(r"Command (.*) is not executable", done.stderr + done.stdout)
    assert found, done.stderr + done.stdout
    return found.group(1)


@pytest.fixture(scope="module")
def mission_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("mission") / "trio.toml"
    path.write_text(MISSION)
    return path


@pytest.mark.parametrize(("field", "value", "accepted"), CASES, ids=IDS)
def test_every_field_refuses_or_quotes_every_character_class(field: str, value: str, accepted: bool,
                                                            mission_file: Path, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "hosts.toml"
    path.write_text(hosts_toml(field, value), encoding="utf-8")
    out = tmp_path / "out"
    status = gen.main([str(mission_file), "--out", str(out), "--hosts", str(path)])
    err = capsys.readouterr().err
    if not accepted:
        assert status == 2, err
        found = re.search(rf"^  {re.escape(field)}: (.*)$", err, re.M) or re.search(rf"{re.escape(field)}: (.*)$", err,
                                                                                      re.M)
        assert found, err
        assert re.search(r"; (remove|give|write|install|set|use)", found.group(1)), err  # the fix
        assert not out.exists()  # nothing written
        return
    assert status == 0, err
    units = sorted(out.glob("hosts/*/systemd/*.service"))
    assert len(units) == 10
    for u in units:
        text = u.read_text()
        host = u.parent.parent.name
        role = "control" if u.name == "tether-start.service" else u.name.removesuffix(".service").split("-")[1]
        template = gen.template_text(role)
        assert directives(text) == directives(template), u  # no injected line
        assert text.count("\n") == template.count("\n"), u
        line = next(ln for ln in text.splitlines() if ln.startswith("ExecStart=")).partition("=")[2]
        argv = systemd_words(line)
        assert parse_unit(u, host).argv == argv, u  # tether rehearse reads the same words
        cfg = BASE["config_dir"] if field != "config_dir" else value
        cfg = str(cfg).replace("{host}", host)
        program = {"router": BASE["python"], "control": BASE["python"]}.get(role, BASE["tether"])
        if field in ("tether", "python") and field == ("python" if role in ("router", "control") else "tether"):
            program = value
        assert argv[0] == program, (u, argv)
        assert argv[argv.index("--zenoh-config" if role != "router" else "--config") + 1].startswith(cfg + "/"), argv
        workdir = next(ln for ln in text.splitlines() if ln.startswith("WorkingDirectory=")).partition("=")[2]
        assert workdir.replace("%%", "%") == cfg
        if role == "recorder":
            rec_out = value if field == "recorder.out" else "/var/lib/t/runs"
            assert argv[argv.index("--out") + 1] == rec_out
            rw = next(ln for ln in text.splitlines() if ln.startswith("ReadWritePaths=")).partition("=")[2]
            assert systemd_words(rw) == [rec_out]
    if SYSTEMD_ANALYZE is not None:  # systemd's own reading of the same quoting
        probe = value.replace("{host}", "agent-1")
        assert systemd_reads_program(probe, tmp_path) == probe


def test_no_unit_is_written_from_a_value_with_a_control_character() -> None:
    """The generator's own guard, below the hosts-file checks: a value that could add a line is refused."""
    values = {"HOST": "agent-1", "NS": "trio", "ID": "1", "NODE": "agent-1", "USER": "tether",
              "CONFIG_DIR": "/etc/tether", "TETHER": "/opt/t/bin/tether\nExecStartPre=/bin/sh", "PYTHON": "/p",
              "OUT": "/o"}
    with pytest.raises(gen.GenerateError, match="control character"):
        gen.unit("agent", values)
    with pytest.raises(gen.GenerateError, match="control character"):
        gen.exec_word("a\rb")
    assert gen.exec_word("/a b/c") == '"/a b/c"' and gen.exec_word("/plain/x.json5") == "/plain/x.json5"
    assert gen.exec_word(";") == '";"' and gen.exec_word("50%") == '"50%%"'


def test_path_problem_names_the_fix() -> None:
    assert hosts.path_problem("/opt/tether venv/bin/tether") is None
    assert "'..'" in (hosts.path_problem("/opt/../bin") or "")
    assert "write '/opt/bin'" in (hosts.path_problem("/opt//bin") or "")
    assert "U+000A at position 4" in (hosts.path_problem("/opt\n") or "")


# --------------------------------------------------------------------------- hardening
def exposure(unit: Path) -> tuple[float, str]:
    """``systemd-analyze security --offline=yes``'s overall exposure of ``unit`` and its word (OK, ...)."""
    done = subprocess.run([SYSTEMD_ANALYZE or "systemd-analyze", "security", "--offline=yes", str(unit)],
                          capture_output=True, text=True, timeout=120)
    found = re.search(r"Overall exposure level for \S+: ([0-9.]+) (\w+)", done.stdout + done.stderr)
    assert found, done.stdout + done.stderr
    return float(found.group(1)), found.group(2)


def settings(text: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for ln in text.splitlines():
        if "=" in ln and not ln.startswith("#"):
            key, _, value = ln.partition("=")
            out.setdefault(key, []).append(value)
    return out


@pytest.mark.skipif(SYSTEMD_ANALYZE is None, reason="systemd-analyze is not installed")
def test_every_generated_unit_is_rated_ok_by_systemd_analyze(tmp_path: Path) -> None:
    """Every unit of a simulated (Section 4) and a Crazyflie (Exp. 1 on Crazyflies) deployment: exposure
    at most 3.0 ("OK"), while keeping what each needs (the control loop's real-time policy, set by
    systemd at exec; the radio's USB devices and cflib's cache directory for a Crazyflie plant)."""
    from tether.catalog import builtin_path

    ratings: dict[str, tuple[float, str]] = {}
    for name in ("section4", "exp1_cf"):
        out = tmp_path / name
        gen.generate(builtin_path(name), out)
        for u in sorted(out.glob("hosts/*/systemd/*.service")):
            ratings[f"{name}/{u.name}"] = exposure(u)
            s = settings(u.read_text())
            role = "control" if u.name == "tether-start.service" else u.name.removesuffix(".service").split("-")[1]
            assert s["CapabilityBoundingSet"] == [""] and s["NoNewPrivileges"] == ["yes"], u
            assert s["ProtectSystem"] == ["strict"] and s["ProtectHome"] == ["yes"], u
            assert (s.get("CPUSchedulingPolicy") == ["rr"]) == (role in ("agent", "plant", "leader", "router",
                                                                           "radio")), u
            crazyflie = role == "radio"
            assert not (name == "exp1_cf" and role == "plant"), u  # a Crazyflie's plant runs in its radio's unit
            assert (s.get("DeviceAllow") == ["char-usb_device rw"]) == crazyflie, u
            assert s["PrivateDevices"][-1] == ("no" if crazyflie else "yes"), u  # the last assignment wins
            if crazyflie:
                assert s["SupplementaryGroups"] == ["plugdev"] and s["DevicePolicy"] == ["closed"]
                cache = s["CacheDirectory"][0]
                assert s["Environment"] == [f"XDG_CACHE_HOME=%C/{cache}"], u  # cflib's TOC cache (toc_cache)
                assert s["TimeoutStopSec"] == ["60"], u  # the dead-man lands the vehicles before the SIGKILL
            if role == "recorder":
                assert s["ReadWritePaths"] == ["/var/lib/tether/runs"]
    for name, (level, word) in ratings.items():
        print(f"{name}: {level} {word}")
    # section4: router, leader, start, recorder, 4 agents and 4 plants; exp1_cf: the same with one radio unit
    assert len(ratings) == 12 + 9, sorted(ratings)
    assert all(level <= 3.0 for level, _ in ratings.values()), ratings


def test_a_crazyflie_plant_caches_its_toc_in_the_units_cache_directory(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """``XDG_CACHE_HOME`` as a radio unit sets it (its ``CacheDirectory=``, which systemd makes the
    user's) is where cflib's TOC cache goes: nothing under the home, which the unit hides."""
    from plant.crazyflie import toc_cache

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "tether-radio-0"))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert toc_cache() == tmp_path / "tether-radio-0" / "tether" / "cf-toc" and toc_cache().is_dir()
    assert not (tmp_path / "home").exists()


@pytest.mark.parametrize("cls", list(CLASSES), ids=list(CLASSES))
def test_a_router_name_with_any_character_class_is_refused(cls: str) -> None:
    """Two sites: a router's name goes into host directories, unit, file and certificate names."""
    m = ms.loads(MISSION)
    text = ('version = 1\n[[routers]]\nname = "ground"\naddress = "10.0.0.1"\n[[routers]]\n'
            f'name = {json.dumps("field" + CLASSES[cls])}\naddress = "10.0.0.2"\nconnect = ["ground"]\n')
    with pytest.raises(hosts.HostsError) as err:
        hosts.plan(m, hosts.loads(text, "h.toml"), "h.toml")
    problems = dict(err.value.problems)
    assert "lower-case name" in problems["routers[1].name"], err.value
