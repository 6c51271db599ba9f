"""Checkouts for the benches that compare builds: a git revision, or this tree as it is, in a
temporary detached ``git worktree`` that is removed when the ``with`` block ends.

    with checked_out("HEAD~1", work / "base") as base, checked_out(None, work / "new") as new:
        ...  # run each side as ``python -m ...`` from inside its own checkout

Both sides of a comparison come from fresh checkouts of the same kind: run from this repository's
own directory, an identical runtime once measured 2–3 % slower than from a worktree, in 6 of 6
pairs (an A/A run). A side runs from its checkout with
``python -m`` (the working directory first on the path, inherited by child processes); pointing only
``PYTHONPATH`` at it from this repository's directory would import this repository.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def is_commit(rev: str) -> bool:
    """Whether ``rev`` names a commit of this repository."""
    return subprocess.run(["git", "-C", str(REPO), "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}"],
                          capture_output=True).returncode == 0


def short(tree: Path) -> str:
    """The abbreviated commit a checkout is at."""
    return subprocess.run(["git", "-C", str(tree), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()


@contextmanager
def checked_out(rev: str | None, into: Path) -> Iterator[Path]:
    """A detached worktree at ``into``: of ``rev``, or (``rev`` None) of HEAD with this tree's
    uncommitted changes applied and its untracked files copied. Removed on leaving, whatever
    happened; ``SystemExit`` naming the revision if git cannot check it out."""
    done = subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(into), rev or "HEAD"],
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{Path(__file__).name}: git cannot check out {rev or 'HEAD'}: {done.stderr.strip()}")
    try:
        if rev is None:
            diff = subprocess.run(["git", "-C", str(REPO), "diff", "HEAD", "--binary"], capture_output=True,
                                  check=True).stdout
            if diff:
                subprocess.run(["git", "-C", str(into), "apply", "--whitespace=nowarn"], input=diff, check=True)
            listed = subprocess.run(["git", "-C", str(REPO), "ls-files", "--others", "--exclude-standard", "-z"],
                                    capture_output=True, check=True).stdout.decode()
            for name in filter(None, listed.split("\0")):
                (into / name).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(REPO / name, into / name)
        yield into
    finally:
        subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(into)], capture_output=True)
