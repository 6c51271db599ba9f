"""Mission files: the catalogue of bad missions, the shipped missions, and the error contract.

Every file in ``tests/missions_bad/`` is a small complete mission, valid except for one defect, that
starts with one or more lines ``# expect: <field> | <substring of the message>``. Loading it must
raise :class:`~tether.mission.MissionError` whose problems include every expected pair and nothing
unexpected. Every message, there and elsewhere, follows the convention ``"<what is wrong>; <how to
fix it>"`` and names its field by its path in the file.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import msgspec
import msgspec.inspect
import pytest

import tether
from tether import mission as ms

BAD = Path(__file__).parent / "missions_bad"
DOC = Path(__file__).parent.parent / "docs" / "mission.md"
SHIPPED = Path(tether.__file__).parent / "missions"
BAD_FILES = sorted(BAD.glob("*.toml"))
SHIPPED_FILES = sorted(SHIPPED.glob("*.toml"))

MIN_CATALOGUE = 100
"""The catalogue must not shrink below this many cases."""

_EXPECT = re.compile(r"^# expect: (?P<field>.+?) \| (?P<text>.+)$")
_PLACE = r"\d+(st|nd|rd|th) \[\[(agents|edges)\]\]"
_TABLE = rf"(agent \d+|edge \d+ → \d+)( \({_PLACE}\))?|{_PLACE}"
_PATH = r"[A-Za-z_][\w-]*(\[\d+\])*(\.[A-Za-z_][\w-]*(\[\d+\])*)*"
_FIELD = re.compile(rf"^(<file>|{_PATH}|({_TABLE})(\.{_PATH})?)$")
"""A field path as messages name it: ``law.kp0[1]``, ``agent 7.offset``, ``edge 3 → 4.weight``,
``2nd [[edges]].from`` (a table without ids), or ``<file>``."""


def _expectations(path: Path) -> list[tuple[str, str]]:
    """The ``(field, substring)`` pairs a catalogue file declares in its ``# expect:`` lines."""
    lines = path.read_bytes().decode("utf-8", errors="replace").splitlines()  # not_utf8.toml is not
    assert lines and _EXPECT.match(lines[0]), f"{path.name}: the first line must be `# expect: <field> | <text>`"
    found = [_EXPECT.match(line) for line in lines]
    return [(m["field"], m["text"]) for m in found if m]


def _assert_well_formed(problems: list[tuple[str, str]]) -> None:
    """Every problem names a field by its path and reads ``"<what is wrong>; <how to fix it>"``."""
    assert problems, "a MissionError must carry at least one problem"
    for field, message in problems:
        assert _FIELD.match(field), f"field {field!r} is not a path in the file"
        assert not re.match(r"^(agents|edges)\[", field), f"{field!r} names a table by its place, not its id or ends"
        what, sep, fix = message.partition("; ")
        assert sep and what.strip() and fix.strip(), f"{field}: {message!r} does not say how to fix it after '; '"
        assert message == message.strip() and "\n" not in message, f"{field}: {message!r}"


def _problems(path: Path) -> list[tuple[str, str]]:
    with pytest.raises(ms.MissionError) as info:
        ms.load(path)
    return info.value.problems


# --------------------------------------------------------------------------- the catalogue
def test_catalogue_is_large_enough() -> None:
    assert len(BAD_FILES) >= MIN_CATALOGUE, f"only {len(BAD_FILES)} bad missions in {BAD}"


@pytest.mark.parametrize("path", BAD_FILES, ids=[p.stem for p in BAD_FILES])
def test_bad_mission_is_rejected_with_its_fix(path: Path) -> None:
    expected = _expectations(path)
    problems = _problems(path)
    _assert_well_formed(problems)
    for field, text in expected:
        assert any(f == field and text in msg for f, msg in problems), (
            f"{path.name}: no problem ({field!r}, ...{text!r}...) in {problems}")
    expected_fields = {field for field, _ in expected}
    unexpected = [(f, msg) for f, msg in problems if f not in expected_fields]
    assert not unexpected, f"{path.name} has one defect but also reports {unexpected}"


def test_catalogue_source_is_named_in_the_error() -> None:
    path = BAD / "rate_zero.toml"
    with pytest.raises(ms.MissionError) as info:
        ms.load(path)
    assert info.value.source == str(path)
    text = str(info.value)
    assert text.startswith(f"{path}: 1 problem(s)")
    assert "  rate: is 0.0 Hz; " in text


# --------------------------------------------------------------------------- shipped missions
def test_there_are_shipped_missions() -> None:
    assert SHIPPED_FILES, f"no missions in {SHIPPED}"


@pytest.mark.parametrize("path", SHIPPED_FILES, ids=[p.stem for p in SHIPPED_FILES])
def test_shipped_mission_loads(path: Path) -> None:
    m = ms.load(path)
    assert ms.validate(m) == []
    assert ms.unreachable_agents(m) == []
    assert m.version == ms.SCHEMA_VERSION


@pytest.mark.parametrize("path", SHIPPED_FILES, ids=[p.stem for p in SHIPPED_FILES])
def test_shipped_mission_round_trips(path: Path) -> None:
    """Decoded, turned back into plain data (the file's names: ``from``/``to``, ``kind``) and decoded
    again, a mission is unchanged; text and file give the same mission."""
    m = ms.load(path)
    data = msgspec.to_builtins(m)
    assert all("from" in e and "to" in e for e in data["edges"])
    assert ms.loads(path.read_text(encoding="utf-8")) == m
    again = msgspec.convert(data, type=ms.Mission)
    assert again == m
    assert ms.validate(again) == []


def test_section4_summary() -> None:
    """The summary fields of the paper's Section 4 mission, as the file states them."""
    m = ms.load(SHIPPED / "section4.toml")
    assert (m.name, m.dim, m.rate, m.duration, m.seed) == ("section4", 2, 100.0, 1000.0, 1)
    assert (m.n, m.steps) == (4, 100_000)
    assert m.dt == pytest.approx(0.01, rel=0, abs=1e-15)
    assert m.agent_ids == [1, 2, 3, 4]
    assert m.leader.id == 5
    assert [m.index_of(i) for i in (1, 2, 3, 4, 5)] == [0, 1, 2, 3, 4]
    assert [(e.src, e.dst, e.weight) for e in m.edges] == [
        (5, 1, 1.0), (1, 2, 1.0), (2, 3, 1.0), (3, 4, 1.0), (4, 1, 1.0)]
    law = m.law
    assert (law.kind, law.kp0, law.kv0, law.gamma_p, law.gamma_v, law.sigma) == ("sigma", 2.0, 2.0, 0.05, 0.05, 1.0)
    assert isinstance(m.leader.profile, ms.ExpAccel)
    assert (m.leader.profile.a0, m.leader.profile.decay) == ([1.0, 0.0], 0.1)
    assert all(isinstance(a.disturbance, ms.Sinusoid) for a in m.agents)
    assert all(isinstance(a.plant, ms.DoubleIntegrator) for a in m.agents)
    assert m.agent(3).offset == [-1.0, 0.0]
    with pytest.raises(KeyError):
        m.agent(5)
    assert m.assumed, "section4 must list what it assumes beyond the paper"


# --------------------------------------------------------------------------- every problem is listed
def _section4_text() -> str:
    return (SHIPPED / "section4.toml").read_text(encoding="utf-8")


def test_two_defects_are_both_reported() -> None:
    text = _section4_text().replace("gamma_p = 0.05", "gamma_p = -1.0").replace("p0 = [1.5, -0.5]", "p0 = [1.5]")
    with pytest.raises(ms.MissionError) as info:
        ms.loads(text, source="two.toml")
    fields = [f for f, _ in info.value.problems]
    assert sorted(fields) == ["agent 1.p0", "law.gamma_p"]
    _assert_well_formed(info.value.problems)
    assert str(info.value).startswith("two.toml: 2 problem(s)")


def test_many_defects_are_all_reported() -> None:
    text = (_section4_text()
            .replace("rate = 100.0", "rate = -1.0")
            .replace("sigma = 1.0", "sigma = 0.0")
            .replace("{ from = 3, to = 4, weight = 1.0 }", "{ from = 3, to = 3, weight = 0.0 }")
            .replace("offset = [0.0, -1.0]", "offset = [0.0, -1.0, 0.0]"))
    with pytest.raises(ms.MissionError) as info:
        ms.loads(text)
    fields = sorted(f for f, _ in info.value.problems)
    assert fields == ["agent 4.offset", "edge 3 → 3", "edge 3 → 3.weight", "law.sigma", "rate"]
    _assert_well_formed(info.value.problems)


def test_assumption1_waits_for_the_ids() -> None:
    """An unknown id is reported alone: reachability on a wrong graph would only add noise."""
    text = _section4_text().replace("{ from = 5, to = 1, weight = 1.0 }", "{ from = 6, to = 1, weight = 1.0 }")
    with pytest.raises(ms.MissionError) as info:
        ms.loads(text)
    assert [f for f, _ in info.value.problems] == ["edge 6 → 1.from"]


def test_nan_is_reported_alone() -> None:
    text = _section4_text().replace("gamma_v = 0.05", "gamma_v = nan").replace("kp0 = 2.0", "kp0 = 0.5")
    with pytest.raises(ms.MissionError) as info:
        ms.loads(text)
    assert [f for f, _ in info.value.problems] == ["law.gamma_v"]


def test_missing_file_is_a_mission_error(tmp_path: Path) -> None:
    with pytest.raises(ms.MissionError) as info:
        ms.load(tmp_path / "absent.toml")
    assert info.value.problems[0][0] == "<file>"
    _assert_well_formed(info.value.problems)


def test_non_utf8_file_is_a_mission_error(tmp_path: Path) -> None:
    path = tmp_path / "latin1.toml"
    path.write_bytes(b'version = 1\nname = "caf\xe9"\n')
    problems = _problems(path)
    assert problems == [("<file>", "is not UTF-8 text; save it as UTF-8")]


# --------------------------------------------------------------------------- decode messages
@pytest.mark.parametrize(
    ("old", "new", "field", "text"),
    [
        ("version = 1", "version = true", "version", "is true"),
        ("version = 1", "version = 1.0", "version", "is 1.0"),
        ('name = "section4"', "name = 4", "name", "is an integer but must be a string"),
        ("seed = 1", "seed = 1.5", "seed", "is a number but must be an integer"),
        ("kp0 = 2.0", 'kp0 = "2"', "law.kp0", "must be a number or an array of numbers"),
        ("kp0 = 2.0", "kp0 = [[2.0], [2.0]]", "law.kp0[0]", "is an array but must be a number"),
        ('kind = "exp_accel"', "kind = 3", "leader.profile.kind", '"waypoints"'),
        ("offset = [1.0, 0.0]", 'offset = [1.0, 0.0]\nplant = "double_integrator"',
         "agent 1.plant", '`plant = { kind = "double_integrator" }`'),
        ("decay = 0.1", "decay = 0.1, dekay = 1.0", "leader.profile.dekay", "rename it to `decay`"),
        ("assumed = [", "assumed = [1, ", "assumed[0]", "is an integer but must be a string"),
    ],
)
def test_decode_messages(old: str, new: str, field: str, text: str) -> None:
    source = _section4_text()
    assert old in source
    with pytest.raises(ms.MissionError) as info:
        ms.loads(source.replace(old, new, 1))
    assert len(info.value.problems) == 1
    _assert_well_formed(info.value.problems)
    got_field, message = info.value.problems[0]
    assert got_field == field and text in message, info.value.problems


def test_field_of_falls_back_to_msgspec_text() -> None:
    """A msgspec message this module does not know still yields a path and a pointer to the docs."""
    field, message = ms._field_of("Expected `int` >= 0 - at `$.agents[0].id`")
    assert field == "agents[0].id"
    assert message.startswith("expected `int` >= 0; ")
    _assert_well_formed(ms.by_id([(field, message)], [None], []))  # an id that did not decode: by place


def test_tables_are_named_by_id_and_ends_not_by_place() -> None:
    """``agents[k]`` / ``edges[k]`` become the agent's id and the edge's ends; the place is added only
    where the id or the ends do not say which table is meant (absent, or repeated in the file)."""
    problems = [("agents[0].offset", "x; y"), ("agents[1].p0[1]", "x; y"), ("agents[2].id", "x; y"),
                ("edges[0].weight", "x; y"), ("edges[1]", "x; y"), ("edges[2].from", "x; y"), ("rate", "x; y")]
    named = [f for f, _ in ms.by_id(problems, [7, 2, 2], [(3, 4), (1, 2), None])]
    assert named == ["agent 7.offset", "agent 2 (2nd [[agents]]).p0[1]", "agent 2 (3rd [[agents]]).id",
                     "edge 3 → 4.weight", "edge 1 → 2", "3rd [[edges]].from", "rate"]
    assert [ms.ordinal(n) for n in (1, 2, 3, 4, 11, 12, 13, 21, 22, 101, 111)] == [
        "1st", "2nd", "3rd", "4th", "11th", "12th", "13th", "21st", "22nd", "101st", "111th"]


# --------------------------------------------------------------------------- per_axis
@pytest.mark.parametrize(
    ("value", "dim", "expanded"),
    [
        (2.0, 2, [2.0, 2.0]),
        (1.5, 3, [1.5, 1.5, 1.5]),
        (2, 3, [2.0, 2.0, 2.0]),
        ([1.0, 2.0], 2, [1.0, 2.0]),
        ([1, 2, 3], 3, [1.0, 2.0, 3.0]),
    ],
)
def test_per_axis(value: ms.PerAxis, dim: int, expanded: list[float]) -> None:
    got = ms.per_axis(value, dim)
    assert got == expanded
    assert all(type(x) is float for x in got)


def test_per_axis_does_not_alias_its_input() -> None:
    value = [1.0, 2.0]
    got = ms.per_axis(value, 2)
    got[0] = 9.0
    assert value == [1.0, 2.0]


def test_per_axis_gains_in_a_mission() -> None:
    text = _section4_text().replace("kp0 = 2.0", "kp0 = [1.5, 3.0]")
    m = ms.loads(text)
    assert ms.per_axis(m.law.kp0, m.dim) == [1.5, 3.0]
    assert ms.per_axis(m.law.kv0, m.dim) == [2.0, 2.0]


# --------------------------------------------------------------------------- docs/mission.md
def _schema_names(t: msgspec.inspect.Type, seen: set[type]) -> set[str]:
    """Every field name and every ``kind`` of the mission schema, as written in a file."""
    names: set[str] = set()
    if isinstance(t, msgspec.inspect.StructType):
        if t.cls in seen:
            return names
        seen.add(t.cls)
        if t.tag_field:
            names |= {t.tag_field, str(t.tag)}
        for f in t.fields:
            names.add(f.encode_name)
            names |= _schema_names(f.type, seen)
    elif isinstance(t, msgspec.inspect.UnionType):
        for member in t.types:
            names |= _schema_names(member, seen)
    elif isinstance(t, msgspec.inspect.ListType):
        names |= _schema_names(t.item_type, seen)
    elif isinstance(t, msgspec.inspect.LiteralType):
        names |= {str(v) for v in t.values if isinstance(v, str)}
    return names


def test_doc_names_every_field_and_kind() -> None:
    doc = DOC.read_text(encoding="utf-8")
    names = _schema_names(msgspec.inspect.type_info(ms.Mission), set())
    assert {"from", "to", "exp_accel", "bounded_random", "double_integrator", "benchmark"} <= names
    missing = sorted(n for n in names if not any(form in doc for form in (f"`{n}`", f".{n}`", f'"{n}"')))
    assert not missing, f"docs/mission.md does not document {missing}"


def test_doc_example_is_a_valid_mission() -> None:
    doc = DOC.read_text(encoding="utf-8")
    blocks = re.findall(r"```toml\n(.*?)```", doc, flags=re.S)
    assert blocks, "docs/mission.md should end with an annotated TOML example"
    for fragment in blocks[:-1]:  # fragments (e.g. a [netem] table) are valid TOML at least
        tomllib.loads(fragment)
    m = ms.loads(blocks[-1], source="docs/mission.md")
    assert (m.dim, m.n, m.steps) == (3, 3, 1500)
    assert isinstance(m.leader.profile, ms.VelocitySchedule)
    assert isinstance(m.agent(3).disturbance, ms.BoundedRandom)
