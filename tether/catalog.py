"""The missions shipped with tether, and how a mission argument is resolved (no heavy imports)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def builtin_path(name: str) -> Path:
    """Path of a mission shipped with tether (``tether/missions/<name>.toml``)."""
    return Path(str(resources.files("tether") / "missions" / f"{name}.toml"))


def builtin_names() -> list[str]:
    root = resources.files("tether") / "missions"
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def resolve(arg: str) -> Path:
    """A mission argument: a path to a file, or the name of a shipped mission."""
    p = Path(arg)
    if p.exists() or arg.endswith(".toml") or "/" in arg:
        return p
    if arg in builtin_names():
        return builtin_path(arg)
    return p
