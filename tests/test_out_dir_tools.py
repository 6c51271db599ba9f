"""The commands besides ``tether run`` that write under an output directory make their files as it
does (``tether/safefs.py``): ``tether deploy-gen`` into an ``--out`` whose names are links to a
root-only file, and into one another user could redirect; ``safefs.Dir.open_append`` (the
rehearsal's logs). The rehearsal's and ``--sitl``'s own checks are in ``tests/test_rehearse.py`` and
``tests/test_sitl.py``. Also the operator's ``tether land``: its own CPU priority, every thread of it."""

from __future__ import annotations

import os
import pwd
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from tether import safefs, sched
from tether import transport as tp
from tests.support import tether, wait_until

REPO = Path(__file__).parent.parent
SECRET = "root only\n"


def secret_file(tmp: Path) -> Path:
    """A file only its owner (root, when the tests run as root) may read or write."""
    secret = tmp / "secret"
    secret.write_text(SECRET)
    secret.chmod(0o600)
    return secret


def untouched(secret: Path) -> None:
    st = os.lstat(secret)
    assert secret.read_text() == SECRET and stat.S_IMODE(st.st_mode) == 0o600 and st.st_nlink == 1


def mode(path: Path) -> int:
    return stat.S_IMODE(os.lstat(path).st_mode)


# --------------------------------------------------------------------------- the append-mode log
def test_an_appended_log_follows_no_link_and_refuses_what_is_not_its_own(tmp_path: Path) -> None:
    secret = secret_file(tmp_path)
    out = safefs.make_out(tmp_path / "out")
    (out / "link.log").symlink_to(secret)
    os.link(secret, out / "hard.log")
    with safefs.Dir.open(out) as d:
        with pytest.raises(safefs.UnsafePath, match="symbolic link"):
            d.open_append("link.log")
        with pytest.raises(safefs.UnsafePath, match="2 names"):
            d.open_append("hard.log")
        for text in (b"first start\n", b"restarted\n"):  # a unit's restarts extend one log
            with d.open_append("unit.log") as fh:
                fh.write(text)
    os.unlink(out / "hard.log")
    untouched(secret)
    assert (out / "unit.log").read_bytes() == b"first start\nrestarted\n"
    assert mode(out / "unit.log") & 0o022 == 0


@pytest.mark.skipif(os.geteuid() != 0, reason="giving a file to another user needs root")
def test_an_appended_log_of_another_user_is_refused(tmp_path: Path) -> None:
    out = safefs.make_out(tmp_path / "out")
    (out / "theirs.log").write_text("theirs\n")
    nobody = pwd.getpwnam("nobody")
    os.chown(out / "theirs.log", nobody.pw_uid, nobody.pw_gid)
    with safefs.Dir.open(out) as d, pytest.raises(safefs.UnsafePath, match="owned by nobody"):
        d.open_append("theirs.log")
    assert (out / "theirs.log").read_text() == "theirs\n"


# --------------------------------------------------------------------------- tether deploy-gen
KEYS = ("hosts/router/tls/router.key", "hosts/agent-1/tls/agent-1.key", "ca/ca.key")
FILES = ("acl.json5", "DEPLOY.md", "hosts/router/router.json5", "hosts/leader/mission.toml",
         "hosts/agent-1/systemd/tether-agent-1.service", "hosts/agent-1/tls/ca.crt",
         "hosts/router/tls/router.key", "hosts/agent-1/tls/agent-1.key")


def generated(out: Path) -> None:
    """What deploy-gen wrote is plain files of this user, keys 0600 in 0700 directories, no
    temporary name left."""
    for d in [out / "ca", *(out / "hosts").glob("*/tls")]:
        st = os.lstat(d)
        assert stat.S_ISDIR(st.st_mode) and mode(d) == 0o700 and st.st_uid == os.geteuid(), d
    keys = sorted(out.rglob("*.key"))
    assert len(keys) == 13, keys  # the CA and 12 processes of Section 4: router, leader, control-0, recorder, 4 x 2
    for key in keys:
        st = os.lstat(key)
        assert stat.S_ISREG(st.st_mode) and mode(key) == 0o600 and st.st_uid == os.geteuid(), key
    for name in FILES:
        st = os.lstat(out / name)
        assert stat.S_ISREG(st.st_mode) and st.st_nlink == 1 and st.st_uid == os.geteuid(), name
    assert not [p for p in out.rglob(".*")], "a temporary name was left behind"


@pytest.mark.slow  # three real deploy-gen runs
def test_deploy_gen_replaces_links_at_its_files_and_refuses_one_at_a_directory(tmp_path: Path) -> None:
    """``--force`` into an earlier output whose file names are now links to a root-only file: each
    link is replaced by the new file (the link is an entry of the user's own ``--out``, and
    ``--force`` is the order to overwrite its files; a rename replaces the entry and never writes
    through it), exit 0, the target untouched. A link where a directory goes (``tls``) is refused
    with exit 2 naming it: following it would put keys where it leads, and replacing it would take
    the removal of a directory tree the command did not make."""
    secret = secret_file(tmp_path)
    out = tmp_path / "out"
    r = tether("deploy-gen", "section4", "--out", str(out))
    assert r.returncode == 0, r.stderr
    generated(out)

    for name in FILES:
        (out / name).unlink()
        (out / name).symlink_to(secret)
    r = tether("deploy-gen", "section4", "--out", str(out), "--force", "--ca", str(out / "ca"))
    assert r.returncode == 0, r.stderr
    untouched(secret)
    generated(out)

    stolen = tmp_path / "stolen"
    stolen.mkdir(mode=0o777)
    tls = out / "hosts" / "agent-1" / "tls"
    for p in tls.iterdir():
        p.unlink()
    tls.rmdir()
    tls.symlink_to(stolen)
    r = tether("deploy-gen", "section4", "--out", str(out), "--force", "--ca", str(out / "ca"))
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert "--out" in r.stderr and f"{tls} is a symbolic link" in r.stderr, r.stderr
    assert list(stolen.iterdir()) == [] and tls.is_symlink()
    untouched(secret)


@pytest.mark.slow  # real deploy-gen runs, refused before they write
def test_deploy_gen_refuses_an_out_others_could_redirect(tmp_path: Path) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    cases = [(shared, "can be written by other users"), (shared / "run", "no sticky bit")]
    if os.geteuid() == 0:
        theirs = tmp_path / "theirs"
        theirs.mkdir()
        nobody = pwd.getpwnam("nobody")
        os.chown(theirs, nobody.pw_uid, nobody.pw_gid)
        cases.append((theirs, "owned by nobody"))
    for out, says in cases:
        r = tether("deploy-gen", "section4", "--out", str(out))
        assert r.returncode == 2, r.stderr
        assert "Traceback" not in r.stderr and "--out" in r.stderr and says in r.stderr, r.stderr
        assert not out.exists() or list(out.iterdir()) == [], f"{out} was written"


# --------------------------------------------------------------------------- the operator's priority
def _policy(tid: int) -> tuple[int, int]:
    return os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority


@pytest.mark.slow  # a real tether land, waiting for a router that is not there
def test_land_runs_every_thread_at_the_gateway_priority_or_says_why_not() -> None:
    """``tether land`` takes ``gateway_priority(DEFAULT_PRIORITY)`` (SCHED_RR 9) before its session
    opens, so Zenoh's threads inherit it; where that is not permitted it runs at the normal policy
    and says so in one warning line."""
    want = sched.gateway_priority(sched.DEFAULT_PRIORITY)
    try:  # whether this user may: a probe in a child, which changes nothing here
        probe = subprocess.run([sys.executable, "-c", f"import os; os.sched_setscheduler(0, os.SCHED_RR, "
                                                      f"os.sched_param({want}))"], capture_output=True, timeout=60)
        permitted = probe.returncode == 0
    except subprocess.TimeoutExpired:
        pytest.fail("the scheduling probe did not end")
    expect = (os.SCHED_RR, want) if permitted else (os.SCHED_OTHER, 0)
    port = tp.free_tcp_port()  # nothing listens there: the command waits out its connect timeout
    proc = subprocess.Popen([sys.executable, "-m", "cli", "land", "--ns", "x", "--connect", f"tcp/127.0.0.1:{port}",
                             "--timeout", "5"], cwd=REPO, env=dict(os.environ, PYTHONPATH=str(REPO)),
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen: dict[int, tuple[int, int]] = {}

    def threads_seen() -> bool:
        try:
            for tid in (int(t) for t in os.listdir(f"/proc/{proc.pid}/task")):
                seen[tid] = _policy(tid)
        except (FileNotFoundError, ProcessLookupError):
            pass
        return len(seen) >= 4  # the main thread and Zenoh's runtime threads

    try:
        wait_until(threads_seen, 30.0, "tether land's Zenoh threads")
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, err  # nothing to send to: the run is not there
    assert set(seen.values()) == {expect}, seen
    lines = [ln for ln in err.splitlines() if "CPU scheduling" in ln]
    assert len(lines) == 1, err
    assert lines[0].startswith("info:" if permitted else "warning:") and (f"SCHED_RR {want}" in lines[0]), lines
