"""The missions shipped with tether, and how a mission argument is resolved (no heavy imports:
every process resolves its mission, so not ``importlib.resources``, which loads ``tempfile``,
``shutil``, ``bz2`` and ``lzma``; tether is installed as files, and its missions are files beside
this module)."""

from __future__ import annotations

from pathlib import Path

MISSIONS = Path(__file__).resolve().parent / "missions"
"""Where the shipped missions are."""


def builtin_path(name: str) -> Path:
    """Path of a mission shipped with tether (``tether/missions/<name>.toml``)."""
    return MISSIONS / f"{name}.toml"


def builtin_names() -> list[str]:
    return sorted(p.name[:-5] for p in MISSIONS.iterdir() if p.name.endswith(".toml"))


def resolve(arg: str) -> Path:
    """A mission argument: a path to a file, or the name of a shipped mission."""
    p = Path(arg)
    if p.exists() or arg.endswith(".toml") or "/" in arg:
        return p
    if arg in builtin_names():
        return builtin_path(arg)
    return p
