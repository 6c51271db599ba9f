"""The documentation holds: every relative link and anchor resolves, the README is short and keeps CI's two
commands, no page reads like a diary, and the Python API page's snippets run."""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
PAGES = sorted([README, ROOT / "CONTRIBUTING.md", *(ROOT / "docs").rglob("*.md")])
README_MAX_LINES = 150

_FENCE = re.compile(r"^(```|~~~).*?^\1[ \t]*$", re.M | re.S)
_CODE_SPAN = re.compile(r"(`+).+?\1", re.S)
_LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_HEADING = re.compile(r"^(#{1,6})[ \t]+(.+?)[ \t]*#*[ \t]*$", re.M)


def _prose(text: str) -> str:
    """``text`` without fenced code blocks and inline code, where a bracket or a ``#`` is not markdown."""
    return _CODE_SPAN.sub("", _FENCE.sub("", text))


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: markup dropped, lower case, punctuation but ``-`` and ``_`` removed,
    spaces turned into hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link in a heading: its text
    text = text.replace("`", "").replace("*", "").lower()
    kept = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LN")
    return kept.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading's anchor in ``path``, repeated headings numbered as GitHub numbers them."""
    seen: dict[str, int] = {}
    out: set[str] = set()
    for m in _HEADING.finditer(_FENCE.sub("", path.read_text(encoding="utf-8"))):
        base = slug(m.group(2))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def links(path: Path) -> list[str]:
    return _LINK.findall(_prose(path.read_text(encoding="utf-8")))


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_every_relative_link_and_anchor_resolves(page: Path) -> None:
    broken = []
    for target in links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto: ...: not ours to check
            continue
        where, _, anchor = target.partition("#")
        dest = (page.parent / where).resolve() if where else page
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading with anchor #{anchor} in {_rel(dest)}")
    assert not broken, f"{_rel(page)}: " + "; ".join(broken)


def test_slugs_follow_github() -> None:
    assert slug("The Crazyflie's link") == "the-crazyflies-link"
    assert slug("`tether run MISSION --sitl`") == "tether-run-mission---sitl"
    assert slug("Settings → config keys (verified)") == "settings--config-keys-verified"
    assert slug("σ against Γ (Remark 4)") == "σ-against-γ-remark-4"


def _ci_commands() -> list[str]:
    """The two README commands as ``.ci/run`` runs them (there with ``-q``, quiet pip)."""
    lines = [ln.strip() for ln in (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()]
    first = lines[lines.index("# README, first command (install + main demo)") + 1]
    second = next(ln for ln in lines[lines.index(next(ln for ln in lines if ln.startswith("# README, second command"))):]
                  if ln.startswith(".venv/bin/pytest"))
    return [first.replace(" -q ", " "), second]


def test_readme_opens_with_the_two_commands_ci_runs() -> None:
    text = README.read_text(encoding="utf-8")
    block = re.search(r"^```sh\n(.*?)^```", text, re.M | re.S)
    assert block is not None, "README.md has no sh block"
    assert text.index(block.group(0)) < 40, "the two commands are README.md's first block"
    assert block.group(1).splitlines() == _ci_commands()


def test_readme_is_short() -> None:
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n < README_MAX_LINES, f"README.md has {n} lines; move detail to docs/ (index: docs/index.md)"


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_no_page_reads_like_a_diary(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    hits = [f"line {i}: {ln.strip()[:80]}" for i, ln in enumerate(text.splitlines(), 1)
            if re.search(r"\bsittings?\b", ln, re.I)]
    assert not hits, f"{_rel(page)} speaks of sittings (history lives in git): " + "; ".join(hits[:5])


def test_the_index_lists_every_page() -> None:
    listed = {(ROOT / "docs" / t.partition("#")[0]).resolve() for t in links(ROOT / "docs" / "index.md")}
    pages = {p.resolve() for p in (ROOT / "docs").glob("*.md") if p.name != "index.md"}
    assert not pages - listed, "docs/index.md does not list " + ", ".join(sorted(p.name for p in pages - listed))


def test_the_api_page_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """docs/api.md's ```python blocks, in order, in one namespace, in an empty folder."""
    blocks = re.findall(r"^```python\n(.*?)^```", (ROOT / "docs" / "api.md").read_text(encoding="utf-8"), re.M | re.S)
    assert blocks, "docs/api.md has no python block"
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {"__name__": "__docs__"}
    for i, code in enumerate(blocks, 1):
        exec(compile(code, f"docs/api.md, python block {i}", "exec"), namespace)
