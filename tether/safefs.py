"""Output directories and the files under them, made without following symbolic links.

Two parts, one trust model:

* :func:`out_problem` checks an output directory (``--out``) before anything starts. Every
  directory on the way to it, symbolic links resolved one at a time, must be owned by root or by
  this user, and may be writable by others only with the sticky bit (as ``/tmp``): otherwise
  someone else could rename a directory of the path and put their own in its place. ``--out``
  itself must be owned by this user and writable by nobody else (a group holding only this user
  aside), sticky bit or not: every process of a run opens its files there by name (the recorder's
  run files, each child's TLS profile and key), so anyone who can create a name there could plant
  one before a process uses it. A symbolic link on the way must be owned by root or this user.
* :class:`Dir` makes what goes under a checked directory. It is opened from ``/`` one component
  at a time with ``O_NOFOLLOW`` (so its path must be a real path, as :func:`make_out` returns);
  sub-directories and files are made relative to its descriptor, never following a link:
  :meth:`Dir.create` exclusively (``O_EXCL``, a key's mode 0600 from its first byte),
  :meth:`Dir.replace` through an exclusive temporary name renamed over the old file (a rename
  replaces a link, it never writes through one), :meth:`Dir.open_log` and :meth:`Dir.open_append`
  refusing anything but a plain file of this user with one name.

Each call blocks for a few system calls. Errors are :class:`OSError` (with the path) or
:class:`UnsafePath`, whose message names the path, the cause and the fix.
"""

from __future__ import annotations

import errno
import grp
import os
import pwd
import secrets
import shutil
import stat
from pathlib import Path
from typing import BinaryIO

MAX_LINKS = 40
"""Symbolic links followed while resolving one path (Linux's own limit, ``MAXSYMLINKS``)."""

_DIR_FLAGS = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC


class UnsafePath(OSError):
    """A path that others could redirect, or an entry that is not what it must be; the message
    says which, and what to do."""


def _group_private(gid: int, uid: int) -> bool:
    """Whether group ``gid`` holds user ``uid`` alone (a user private group, as a umask of 002
    makes directories group-writable for): no other user has it as primary group or is listed."""
    try:
        group = grp.getgrgid(gid)
        name = pwd.getpwuid(uid).pw_name
    except KeyError:
        return False
    if any(member != name for member in group.gr_mem):
        return False
    return all(p.pw_uid == uid for p in pwd.getpwall() if p.pw_gid == gid)


def _others_write(st: os.stat_result) -> bool:
    """Whether someone other than the owner may create or rename entries in directory ``st``."""
    if st.st_mode & stat.S_IWOTH:
        return True
    return bool(st.st_mode & stat.S_IWGRP) and not _group_private(st.st_gid, st.st_uid)


def _who(uid: int) -> str:
    try:
        return f"{pwd.getpwuid(uid).pw_name} (uid {uid})"
    except KeyError:
        return f"uid {uid}"


def out_problem(path: Path) -> str | None:
    """What makes ``path`` unsafe as an output directory (module docstring), as one line naming
    the path at fault and the fix (the caller puts its option's name first); ``None`` when it is
    safe. A missing ``path`` is judged by the directory it would be made in. Blocks for a few
    ``lstat`` calls."""
    me = os.geteuid()
    todo = list(Path(os.path.join(os.getcwd(), path)).parts[1:])
    cur = Path("/")
    links = 0
    st = os.lstat(cur)
    while True:
        last = not todo
        if stat.S_ISDIR(st.st_mode):
            if last:
                if st.st_uid != me:
                    return (f"{cur} is owned by {_who(st.st_uid)}, not by {_who(me)} who runs this; "
                            f"give a directory of your own (it is made if missing)")
                if _others_write(st):
                    return (f"{cur} can be written by other users (mode {stat.S_IMODE(st.st_mode):04o}); "
                            f"`chmod go-w {cur}` or give a directory only you can write")
            elif st.st_uid not in (0, me):
                return (f"{cur}, on the way to {path}, is owned by {_who(st.st_uid)}, who could replace "
                        "what is below it; give a directory under one owned by you or root")
            elif _others_write(st) and not st.st_mode & stat.S_ISVTX:
                return (f"{cur}, on the way to {path}, can be written by other users and has no sticky "
                        f"bit (mode {stat.S_IMODE(st.st_mode):04o}), so they could replace what is below it; "
                        f"`chmod o-w,g-w {cur}` or `chmod +t {cur}`, or give another directory")
        if last:
            return None
        comp = todo.pop(0)
        if comp in ("", "."):
            continue
        if comp == "..":
            cur = cur.parent
            st = os.lstat(cur)
            continue
        nxt = cur / comp
        try:
            st = os.lstat(nxt)
        except FileNotFoundError:
            return None  # made below `cur`, whose check passed
        if stat.S_ISLNK(st.st_mode):
            if st.st_uid not in (0, me):
                return (f"{nxt} is a symbolic link owned by {_who(st.st_uid)}, who chooses where it "
                        "leads; give a path without it")
            links += 1
            if links > MAX_LINKS:
                return f"{path} has more than {MAX_LINKS} symbolic links on its way (a loop?); give a real path"
            target = os.readlink(nxt)
            todo = [*Path(target).parts, *todo]
            if os.path.isabs(target):
                todo = todo[1:]
                cur = Path("/")
            st = os.lstat(cur)
            continue
        if not stat.S_ISDIR(st.st_mode):
            return f"{nxt} is not a directory; give a directory (it is made if missing)"
        cur = nxt


def real_out(path: Path) -> Path:
    """The real path ``path`` names (symbolic links resolved; missing components kept), for
    :class:`Dir`, which follows none."""
    return Path(os.path.realpath(path))


def make_out(path: Path, arg: str = "--out") -> Path:
    """Check ``path`` (:func:`out_problem`; :class:`UnsafePath` with its line), make its missing
    directories (mode 0755 less the umask, each relative to its parent's descriptor) and return
    its real path. Raises :class:`OSError` when a directory cannot be made."""
    problem = out_problem(path)
    if problem is not None:
        raise UnsafePath(errno.EPERM, f"{arg}: {problem}")
    real = real_out(path)
    missing: list[str] = []
    base = real
    while not base.exists():
        missing.insert(0, base.name)
        base = base.parent
    with Dir.open(base) as d:
        fd = os.dup(d.fd)
    try:
        for name in missing:
            try:
                os.mkdir(name, 0o755, dir_fd=fd)
            except FileExistsError:
                pass
            nfd = os.open(name, _DIR_FLAGS, dir_fd=fd)
            os.close(fd)
            fd = nfd
            _own(os.fstat(fd), base / name, directory=True)
            base = base / name
    finally:
        os.close(fd)
    return real


def _own(st: os.stat_result, path: Path, directory: bool) -> None:
    """:class:`UnsafePath` unless ``st`` is this user's directory (``directory``) or plain file
    with one name."""
    if directory and not stat.S_ISDIR(st.st_mode):
        raise UnsafePath(errno.ENOTDIR, f"{path} is not a directory; remove it")
    if not directory and not stat.S_ISREG(st.st_mode):
        raise UnsafePath(errno.EINVAL, f"{path} is not a plain file; remove it")
    if st.st_uid != os.geteuid():
        raise UnsafePath(errno.EPERM, f"{path} is owned by {_who(st.st_uid)}, not by {_who(os.geteuid())}; "
                                      "remove it or give another --out")
    if not directory and st.st_nlink != 1:
        raise UnsafePath(errno.EMLINK, f"{path} has {st.st_nlink} names (a hard link to another file?); "
                                       "remove it")


class Dir:
    """An open directory (a descriptor) whose entries are made without following links. Use as a
    context manager, or :meth:`close` it."""

    def __init__(self, fd: int, path: Path) -> None:
        self.fd = fd
        self.path = path
        """Where it is (for messages and for processes that open files by name)."""
        self.final: tuple[Dir, str] | None = None
        """Where :meth:`commit` puts a directory from :meth:`fresh`."""

    @classmethod
    def open(cls, path: Path) -> Dir:
        """Open the directory at real path ``path`` from ``/``, one component at a time, following
        no link (:class:`UnsafePath` if a component is one, or is not a directory)."""
        fd = os.open("/", _DIR_FLAGS)
        cur = Path("/")
        try:
            for comp in Path(os.path.abspath(path)).parts[1:]:
                cur = cur / comp
                try:
                    nfd = os.open(comp, _DIR_FLAGS, dir_fd=fd)
                except OSError as exc:
                    if exc.errno in (errno.ELOOP, errno.ENOTDIR):
                        raise UnsafePath(exc.errno, f"{cur} is a symbolic link or not a directory; "
                                                    "remove it or give its real path") from None
                    raise OSError(exc.errno, exc.strerror, str(cur)) from None
                os.close(fd)
                fd = nfd
        except BaseException:
            os.close(fd)
            raise
        return cls(fd, cur)

    def __enter__(self) -> Dir:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1

    def sub(self, name: str, private: bool = False) -> Dir:
        """Sub-directory ``name``, made if missing (0700 if ``private``, else 0755 less the umask),
        opened without following a link; it must be this user's (:class:`UnsafePath`). A
        ``private`` one is set to mode 0700 through its descriptor."""
        try:
            os.mkdir(name, 0o700 if private else 0o755, dir_fd=self.fd)
        except FileExistsError:
            pass
        try:
            fd = os.open(name, _DIR_FLAGS, dir_fd=self.fd)
        except OSError as exc:
            if exc.errno in (errno.ELOOP, errno.ENOTDIR):
                raise UnsafePath(exc.errno, f"{self.path / name} is a symbolic link or not a directory; "
                                            "remove it") from None
            raise OSError(exc.errno, exc.strerror, str(self.path / name)) from None
        try:
            _own(os.fstat(fd), self.path / name, directory=True)
            if private:
                os.fchmod(fd, 0o700)
        except BaseException:
            os.close(fd)
            raise
        return Dir(fd, self.path / name)

    def fresh(self, name: str) -> Dir:
        """A new private directory (mode 0700) named ``name`` in place of whatever was there: built
        under an exclusive random name, then renamed over ``name`` by :meth:`commit` (a link at
        ``name`` is replaced, never followed; an earlier directory there is removed first)."""
        for _ in range(100):
            tmp = f".{name}.{secrets.token_hex(6)}"
            try:
                os.mkdir(tmp, 0o700, dir_fd=self.fd)
            except FileExistsError:
                continue
            d = self.sub(tmp, private=True)
            d.final = (self, name)
            return d
        raise UnsafePath(errno.EEXIST, f"cannot make a directory in {self.path}: every name tried exists")

    def commit(self) -> Path:
        """Rename a directory from :meth:`fresh` to its name; its path then."""
        assert self.final is not None, "commit() of a directory not made by fresh()"
        parent, name = self.final
        for _ in range(1000):  # someone who may write the parent can put an entry back: remove it again
            try:
                st = os.lstat(name, dir_fd=parent.fd)
            except FileNotFoundError:
                st = None
            if st is not None and stat.S_ISDIR(st.st_mode):
                shutil.rmtree(name, dir_fd=parent.fd)
            elif st is not None:
                parent.remove(name)  # a link or a file: the entry itself, never what it names
            try:
                os.rename(self.path.name, name, src_dir_fd=parent.fd, dst_dir_fd=parent.fd)
                break
            except OSError as exc:
                if exc.errno not in (errno.ENOTDIR, errno.EEXIST, errno.ENOTEMPTY, errno.EISDIR):
                    raise OSError(exc.errno, exc.strerror, str(parent.path / name)) from None
        else:
            raise UnsafePath(errno.EEXIST, f"{parent.path / name} came back 1000 times while being replaced: "
                                           "someone else writes in its directory; give another --out")
        self.path = parent.path / name
        self.final = None
        return self.path

    def discard(self) -> None:
        """Remove a directory from :meth:`fresh` that was not committed."""
        if self.final is not None:
            parent, _ = self.final
            shutil.rmtree(self.path.name, dir_fd=parent.fd, ignore_errors=True)
            self.final = None

    def create(self, name: str, data: bytes, mode: int = 0o600) -> Path:
        """Write new file ``name`` with ``data``, made exclusively (``O_EXCL``: an existing entry,
        a link included, is :class:`FileExistsError`) with ``mode`` from its creation."""
        try:
            fd = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, mode,
                         dir_fd=self.fd)
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror, str(self.path / name)) from None
        try:
            os.fchmod(fd, mode)  # whatever the umask
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
        finally:
            os.close(fd)
        return self.path / name

    def open_new(self, name: str, mode: int = 0o644) -> BinaryIO:
        """A new file ``name`` opened for writing, made exclusively (``O_EXCL``: an existing entry, a
        link included, is :class:`FileExistsError`) with ``mode``; for a writer that streams (a run
        file's ``.part``, then :meth:`rename`)."""
        path = self.path / name

        def opener(_: str, flags: int) -> int:
            fd = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, mode,
                         dir_fd=self.fd)
            os.fchmod(fd, mode)
            return fd

        return open(path, "wb", opener=opener)

    def rename(self, src: str, dst: str) -> Path:
        """Rename entry ``src`` to ``dst`` in this directory (an entry at ``dst`` is replaced, never
        followed); the new path."""
        try:
            os.rename(src, dst, src_dir_fd=self.fd, dst_dir_fd=self.fd)
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror, str(self.path / dst)) from None
        return self.path / dst

    def replace(self, name: str, data: bytes, mode: int = 0o644) -> Path:
        """Write file ``name`` with ``data`` in place of any earlier one: made under an exclusive
        temporary name, then renamed over ``name`` (which replaces a link and never follows it)."""
        tmp = f".{name}.{secrets.token_hex(6)}.part"
        self.create(tmp, data, mode)
        try:
            return self.rename(tmp, name)
        except OSError:
            os.unlink(tmp, dir_fd=self.fd)
            raise

    def open_log(self, name: str) -> BinaryIO:
        """File ``name`` opened for writing from its start (made if missing, mode 0644 less the
        umask), never through a link; an existing entry must be this user's plain file with one
        name (:class:`UnsafePath`), and is truncated only once that is known."""
        return self._open_own(name, "wb", truncate=True)

    def open_append(self, name: str) -> BinaryIO:
        """File ``name`` opened for appending (made if missing, mode 0644 less the umask), never
        through a link (``O_NOFOLLOW``); an existing entry must be this user's plain file with one
        name (:class:`UnsafePath`). For a log that several starts of one process extend (a unit
        restarted by its ``Restart=``)."""
        return self._open_own(name, "ab", truncate=False)

    def _open_own(self, name: str, mode: str, truncate: bool) -> BinaryIO:
        """``name`` opened in ``mode`` (``"wb"`` never truncates before the check), never through a
        link, checked to be this user's plain file with one name, then truncated if asked."""
        path = self.path / name

        def opener(_: str, flags: int) -> int:
            return os.open(name, (flags & ~os.O_TRUNC) | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644, dir_fd=self.fd)

        try:
            fh = open(path, mode, opener=opener)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise UnsafePath(exc.errno, f"{path} is a symbolic link; remove it") from None
            raise
        try:
            _own(os.fstat(fh.fileno()), path, directory=False)
            if truncate:
                fh.truncate(0)
        except BaseException:
            fh.close()
            raise
        return fh  # type: ignore[return-value]

    def remove(self, name: str) -> None:
        """Remove entry ``name`` (a file or a link, never what a link names); missing is fine."""
        try:
            os.unlink(name, dir_fd=self.fd)
        except FileNotFoundError:
            pass


def write_file(path: Path, data: bytes, mode: int = 0o644) -> Path:
    """:meth:`Dir.replace` of ``path.name`` in its directory, a real path (``Dir.open``)."""
    with Dir.open(path.parent) as d:
        return d.replace(path.name, data, mode)
