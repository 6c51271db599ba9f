"""``--out`` and what goes under it: made following no link, keys private, an ``--out`` that
another user could redirect refused before anything starts (``tether/safefs.py``,
``deploy/local.py``, ``deploy/localtls.py``, ``deploy/pki.py``)."""

from __future__ import annotations

import os
import pwd
import stat
import subprocess
import threading
from pathlib import Path

import pytest

from tether import safefs
from tests.support import tether, wait_until

as_root = pytest.mark.skipif(os.geteuid() != 0, reason="giving a file to another user needs root")


def _nobody() -> tuple[int, int]:
    p = pwd.getpwnam("nobody")
    return p.pw_uid, p.pw_gid


def _refused_before_start(r: subprocess.CompletedProcess[str], out: Path, *words: str) -> None:
    assert "Traceback" not in r.stderr, r.stderr
    assert r.returncode == 2, f"status {r.returncode}\n{r.stderr}"
    for word in ("--out", *words):
        assert word in r.stderr, f"{word!r} not in\n{r.stderr}"
    assert "router listening" not in r.stderr and "identities made" not in r.stderr, r.stderr
    assert not (out / "run.npz").exists() and not (out / "tls").exists()


# --------------------------------------------------------------------------- the check
def test_an_own_private_out_passes_and_one_others_may_write_does_not(tmp_path: Path) -> None:
    own = tmp_path / "own"
    own.mkdir(mode=0o755)
    assert safefs.out_problem(own) is None
    assert safefs.out_problem(own / "missing" / "deeper") is None  # made in `own`

    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    problem = safefs.out_problem(shared)
    assert problem is not None and "can be written by other users" in problem and "chmod go-w" in problem
    problem = safefs.out_problem(shared / "run")  # others could rename `run` and put theirs in its place
    assert problem is not None and "no sticky bit" in problem and "on the way" in problem

    sticky = tmp_path / "sticky"
    sticky.mkdir()
    sticky.chmod(0o1777)
    assert safefs.out_problem(sticky / "run") is None  # as /tmp: others cannot rename what is ours
    problem = safefs.out_problem(sticky)  # but they could plant names in --out itself
    assert problem is not None and "can be written by other users" in problem

    file = tmp_path / "file"
    file.write_text("x")
    problem = safefs.out_problem(file / "run")
    assert problem is not None and "not a directory" in problem


@as_root
def test_an_out_owned_by_another_user_or_reached_through_their_link_is_named(tmp_path: Path) -> None:
    uid, gid = _nobody()
    theirs = tmp_path / "theirs"
    theirs.mkdir(mode=0o755)
    os.chown(theirs, uid, gid)
    problem = safefs.out_problem(theirs)
    assert problem is not None and "owned by nobody" in problem and "give a directory of your own" in problem
    problem = safefs.out_problem(theirs / "run")
    assert problem is not None and "on the way" in problem and "owned by nobody" in problem

    mine = tmp_path / "mine"
    mine.mkdir()
    link = tmp_path / "link"
    link.symlink_to(mine)
    assert safefs.out_problem(link) is None  # a link of this user's: followed, its target checked
    os.lchown(link, uid, gid)
    problem = safefs.out_problem(link)
    assert problem is not None and "symbolic link owned by nobody" in problem


# --------------------------------------------------------------------------- the primitives
def test_files_are_made_without_following_links(tmp_path: Path) -> None:
    secret = tmp_path / "secret"
    secret.write_text("root only\n")
    secret.chmod(0o600)
    out = tmp_path / "out"
    real = safefs.make_out(out)
    assert real == out.resolve() and out.is_dir()
    (out / "key").symlink_to(secret)
    (out / "log").symlink_to(secret)
    (out / "events.json").symlink_to(secret)
    os.link(secret, out / "hard.log")
    with safefs.Dir.open(real) as d:
        with pytest.raises(FileExistsError):
            d.create("key", b"attacker's bytes")
        with pytest.raises(safefs.UnsafePath, match="symbolic link"):
            d.open_log("log")
        with pytest.raises(safefs.UnsafePath, match="2 names"):
            d.open_log("hard.log")
        d.replace("events.json", b"[]\n")  # the link is replaced, not written through
        made = d.create("new.key", b"k", 0o600)
        (out / "run.npz.part").symlink_to(secret)
        with pytest.raises(FileExistsError):
            d.open_new("run.npz.part")
        d.remove("run.npz.part")  # the link itself
        with d.open_new("run.npz.part") as fh:
            fh.write(b"PK")
        d.rename("run.npz.part", "run.npz")
        with d.open_log("agent-1.log") as fh:
            fh.write(b"line\n")
    assert secret.read_text() == "root only\n"
    assert (out / "events.json").read_text() == "[]\n" and not (out / "events.json").is_symlink()
    assert stat.S_IMODE(made.stat().st_mode) == 0o600
    assert (out / "run.npz").read_bytes() == b"PK" and secret.exists()
    (tmp_path / "hop").symlink_to(out)
    with pytest.raises(safefs.UnsafePath, match="symbolic link"):
        safefs.Dir.open(tmp_path / "hop")


def test_a_fresh_private_directory_replaces_a_link_and_never_writes_through_it(tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out = safefs.make_out(tmp_path / "out")
    (out / "tls").symlink_to(elsewhere)
    with safefs.Dir.open(out) as d, d.fresh("tls") as tls:
        tls.create("a.key", b"secret", 0o600)
        tls.commit()
    assert list(elsewhere.iterdir()) == []
    st = os.lstat(out / "tls")
    assert stat.S_ISDIR(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o700 and st.st_uid == os.geteuid()
    assert (out / "tls" / "a.key").read_bytes() == b"secret"
    assert sorted(p.name for p in out.iterdir()) == ["tls"]  # no temporary name left


# --------------------------------------------------------------------------- real runs
@pytest.mark.slow
def test_a_run_refuses_an_out_others_could_redirect_before_anything_starts(tmp_path: Path) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    r = tether("run", "section4", "--out", str(shared), "--duration", "1", "--quiet")
    _refused_before_start(r, shared, "can be written by other users")
    assert not (shared / "logs").exists()

    r = tether("run", "section4", "--out", str(shared / "run"), "--duration", "1", "--quiet")
    _refused_before_start(r, shared / "run", "no sticky bit")
    assert not (shared / "run").exists()

    if os.geteuid() == 0:
        theirs = tmp_path / "theirs"
        theirs.mkdir()
        os.chown(theirs, *_nobody())
        r = tether("run", "section4", "--out", str(theirs), "--duration", "1", "--quiet")
        _refused_before_start(r, theirs, "owned by nobody")
        assert not (theirs / "logs").exists()


@pytest.mark.slow
def test_a_symlinked_log_is_not_followed_and_the_run_refuses(tmp_path: Path) -> None:
    secret = tmp_path / "secret"
    secret.write_text("root only\n")
    secret.chmod(0o600)
    out = tmp_path / "out"
    (out / "logs").mkdir(parents=True)
    (out / "logs" / "agent-2.log").symlink_to(secret)
    r = tether("run", "section4", "--out", str(out), "--duration", "1", "--quiet")
    _refused_before_start(r, out, "agent-2.log is a symbolic link")
    assert secret.read_text() == "root only\n" and stat.S_IMODE(secret.stat().st_mode) == 0o600
    assert sorted(p.name for p in (out / "logs").iterdir()) == ["agent-2.log"]  # no other log left behind


@pytest.mark.slow
def test_a_tls_swapped_for_a_link_while_it_is_made_gets_no_key(tmp_path: Path) -> None:
    """``tls`` is a link to a directory an attacker reads, and a thread puts the link back whenever
    the name is free, until the run's own ``tls/`` is in place: no key reaches the attacker's
    directory, and the run's are mode 0600 in a 0700 directory of the runner's."""
    stolen = tmp_path / "stolen"
    stolen.mkdir(mode=0o777)
    out = tmp_path / "out"
    out.mkdir()
    tls = out / "tls"
    tls.symlink_to(stolen)
    done = threading.Event()
    swaps = 0

    def attacker() -> None:
        nonlocal swaps
        while not done.is_set():
            try:
                os.symlink(stolen, tls)
                swaps += 1
            except FileExistsError:
                if os.path.isdir(tls) and not os.path.islink(tls):
                    return  # the run's own directory: another user could not remove it
                try:
                    os.unlink(tls)  # a link (ours), or the run's directory mid-rename (EISDIR)
                except OSError:
                    pass

    thread = threading.Thread(target=attacker, daemon=True)
    thread.start()
    try:
        r = tether("run", "section4", "--out", str(out), "--duration", "1", "--quiet")
    finally:
        done.set()
        thread.join(timeout=10)
    assert r.returncode == 0, r.stderr[-3000:]
    assert swaps > 0
    assert list(stolen.iterdir()) == []
    st = os.lstat(tls)
    assert stat.S_ISDIR(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o700 and st.st_uid == os.geteuid()
    keys = sorted(tls.glob("*.key"))
    assert len(keys) == 9, keys  # router, gateway, control-0, leader, 4 agents, recorder
    for key in keys:
        ks = os.lstat(key)
        assert stat.S_ISREG(ks.st_mode) and stat.S_IMODE(ks.st_mode) == 0o600 and ks.st_uid == os.geteuid(), key
    assert not [p for p in out.iterdir() if p.name.startswith(".tls.")]
    wait_until(lambda: not thread.is_alive(), 10.0, "the attacker thread to end")
