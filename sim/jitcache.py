"""The compile cache's freshness: a kernel goes stale with the functions it calls, not only with its own file.

numba keys a cached kernel on its own source file alone (its content hash): a kernel of
``sim/lockstep_kernel.py`` that calls the supervisor's rule (``agent/safety.py``), the failsafe laws
(``tether/failsafe.py``) or a law's step (``agent/laws/``) is loaded from the cache after any of
those changed, and runs the old code (numba's documented limitation: "changes in other files are
not detected"). An upgrade that changes only ``tether/failsafe.py`` would fly the new failsafe in
``tether run`` and the old one in ``tether sweep``.

:func:`install` puts locators in front of numba's own that cache every function of tether's files
(and of the generated law modules, :mod:`sim.lawkernels`) where numba would, stamped with its own
file's hash *and* the hash of :data:`SOURCES`: an edit of any of them compiles every kernel afresh.
:func:`digest` is that hash (no numba import: :func:`sim.warm.prewarm_stamp` reads it too).
"""

from __future__ import annotations

import functools
import hashlib
import os
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
"""The tree tether's packages live in."""
ROOTS: list[Path] = [ROOT / pkg for pkg in ("agent", "sim", "tether", "plant", "netem")]
"""Directories whose files' functions are cached with :data:`SOURCES`' stamp: tether's packages
whose functions are compiled (not the tree: a virtual environment may live in it); the generated law
modules' directory is added where it is."""

SOURCES: tuple[str, ...] = ("sim/kernel.py", "sim/lockstep_kernel.py", "sim/lawkernels.py", "agent/safety.py",
                            "tether/failsafe.py", "tether/vec.py", "agent/laws")
"""The files (a directory: its ``*.py``) whose functions the compiled kernels call, relative to
:data:`ROOT` (or absolute). Every kernel's cache stamp holds their hash."""


def files() -> list[Path]:
    """:data:`SOURCES` as files, in a fixed order."""
    out: list[Path] = []
    for rel in SOURCES:
        p = Path(rel) if os.path.isabs(rel) else ROOT / rel
        out += sorted(p.glob("*.py")) if p.is_dir() else [p]
    return out


@functools.lru_cache(maxsize=None)
def _hash_file(path: str, mtime_ns: int, size: int) -> bytes:  # keyed on the stat: re-read when it changes
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).digest()


def digest() -> str:
    """The hash of :data:`SOURCES`' contents (hex); a file read again only when its stat changes."""
    h = hashlib.sha256()
    for f in files():
        st = f.stat()
        h.update(f.name.encode() + b"\0" + _hash_file(str(f), st.st_mtime_ns, st.st_size))
    return h.hexdigest()


def ours(py_file: str) -> bool:
    """Whether ``py_file`` is one of tether's files or a generated law module."""
    from sim import lawkernels

    path = Path(py_file).resolve()
    return any(path.is_relative_to(d) for d in (*ROOTS, lawkernels.cache_dir().resolve()))


_INSTALLED: list[Any] = []


def install() -> bool:
    """Put the tracking locators in front of numba's (once per process); False where numba is
    missing or its caching machinery is not the one this was written against (numba's own locators
    then apply, as before)."""
    if _INSTALLED:
        return True
    try:
        from numba.core import caching
    except ImportError:
        return False
    impl = getattr(caching, "CacheImpl", None)
    found = [getattr(caching, n, None) for n in ("UserProvidedCacheLocator", "InTreeCacheLocator",
                                                  "UserWideCacheLocator")]
    bases: list[type] = [b for b in found if isinstance(b, type)]
    if impl is None or not isinstance(getattr(impl, "_locator_classes", None), list) or len(bases) < len(found):
        return False

    class Tracked:
        """A numba locator for tether's files: numba's place, a stamp that follows :data:`SOURCES`."""

        @classmethod
        def from_function(cls, py_func: Any, py_file: str) -> Any:
            if not ours(py_file):
                return None
            return super().from_function(py_func, py_file)  # type: ignore[misc]

        def get_source_stamp(self) -> Any:
            return (super().get_source_stamp(), digest())  # type: ignore[misc]

    made = [type(f"Tracked{b.__name__}", (Tracked, b), {"__module__": __name__}) for b in bases]
    impl._locator_classes[:0] = made
    _INSTALLED.extend(made)
    return True


def locators() -> tuple[Any, ...]:
    """The locator classes :func:`install` put in place (empty before, or without numba)."""
    return tuple(_INSTALLED)
