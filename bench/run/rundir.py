"""Who may write a run directory, and what ``--out`` may be.

A run directory has one writer: the process that holds the exclusive lock on its
:data:`LOCK_FILE` (:class:`RunLock`), taken before the run's first write and held until the
process exits — for a new run, a ``--resume`` and a ``--cluster`` run alike (the cluster's
workers never write the directory; the client does).  A second process asking for it gets a
:class:`LockHeld` naming the holder (pid, host, start time, command) recorded in the lock file.

``--out`` must be absent or an empty directory (:func:`claim_out`), or with ``--resume`` a run
directory: anything else found there is named in the error, never overwritten.  A run refused
after its claim gives back a directory it created and wrote nothing to (:meth:`RunLock.discard`).

Why ``fcntl.flock`` and no library (``filelock``, ``portalocker``): the lock is advisory on one
POSIX file system, which is exactly what a run directory needs; the kernel drops it when the
holder dies (a SIGKILLed run leaves no stale lock to clean up, unlike a pid file); and it is one
stdlib call.  Limits: on NFS, ``flock`` may lock only on the local host (Linux ≥ 2.6.12 emulates it
with POSIX byte-range locks there); Windows has no ``fcntl`` (isobench targets Linux and macOS).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import socket
import sys
from pathlib import Path

#: the lock file inside a run directory; kept after the run (its text names the last holder):
#: removing it while another process waits on it would let two processes lock two files
LOCK_FILE = ".isobench.lock"


class LockHeld(ValueError):
    """The run directory is locked by another process (the message names it and the fix)."""


class OutError(ValueError):
    """``--out`` cannot be used (a file, not creatable, not empty); the message names what was found."""


def _alive(pid) -> bool:
    """Whether a process with id ``pid`` exists on this host (one we may not signal counts)."""
    try:
        os.kill(int(pid), 0)
    except PermissionError:
        return True
    except (OSError, ValueError, TypeError, OverflowError):
        return False
    return True


def _holder(path: Path) -> str:
    """The holder recorded in the lock file at ``path``, as a phrase.  The file keeps the last
    holder's record after it ends (:data:`LOCK_FILE`), and a new holder rewrites it just after
    taking the lock: a record naming a process of this host that no longer runs is that earlier
    holder's, and the holder is then one still starting."""
    try:
        rec = json.loads(path.read_text() or "{}")
    except (OSError, ValueError):
        rec = {}
    if not isinstance(rec, dict) or (rec.get("host") == socket.gethostname() and not _alive(rec.get("pid"))):
        rec = {}
    if not rec:
        return "another process (still starting: it has not recorded itself yet)"
    return (f"pid {rec.get('pid', '?')} on {rec.get('host', '?')}, since {rec.get('started', '?')} "
            f"({rec.get('command', '?')[:120]})")


class RunLock:
    """The exclusive lock on ``run_dir``/:data:`LOCK_FILE`.  :meth:`acquire` takes it without
    waiting (:class:`LockHeld` when another open file description holds it — another process, or
    another ``RunLock`` in this one) and records this process in the file; :meth:`release` (or
    process exit) frees it.  ``run_dir`` must exist."""

    def __init__(self, run_dir: Path):
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK_FILE
        self._fd: int | None = None
        #: the directories :func:`claim_out` created for this claim, ``run_dir`` first (:meth:`discard`)
        self.created: list[Path] = []

    def acquire(self) -> "RunLock":
        import fcntl

        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise LockHeld(f"--out: {self.run_dir} is being written by {_holder(self.path)}; a run directory has "
                           "one writer: wait for it to finish, or pass another --out") from None
        except OSError:
            os.close(fd)
            raise
        if not _same_file(fd, self.path):  # removed by a holder that gave the directory up (discard)
            os.close(fd)
            raise LockHeld(f"--out: {self.run_dir} was given up by the process that held it as this one claimed it; "
                           "run the command again")
        rec = {"pid": os.getpid(), "host": socket.gethostname(),
               "started": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
               "command": " ".join([os.path.basename(sys.executable), *sys.argv])}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(rec).encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        """Free the lock (the file stays, see :data:`LOCK_FILE`); idempotent."""
        if self._fd is not None:
            os.close(self._fd)  # closing the only descriptor releases the flock
            self._fd = None

    close = release

    def discard(self) -> None:
        """Release the lock, first removing the run directory when :func:`claim_out` created it
        for this claim and it still holds nothing but the lock file (with the parents it created):
        a run refused after its claim (an argument checked only once the backends are loaded)
        leaves nothing behind.  Done under the lock, so no other process writes the directory;
        one that opened the lock file meanwhile finds it removed when it gets the lock
        (:meth:`acquire`).  A directory that holds anything else is kept as it is."""
        try:
            if self._fd is not None and self.created and not foreign_files(self.run_dir):
                self.path.unlink()
                for d in self.created:
                    d.rmdir()
        except OSError:  # something appeared in it (or above it) meanwhile: it stays
            pass
        finally:
            self.release()

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _same_file(fd: int, path: Path) -> bool:
    """Whether ``path`` still names the file open as ``fd``."""
    try:
        a, b = os.fstat(fd), os.stat(path)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def _missing_dirs(path: Path) -> list[Path]:
    """``path`` and its ancestors that do not exist yet, deepest first."""
    missing, p = [], Path(path).absolute()
    while not p.exists() and p != p.parent:
        missing.append(p)
        p = p.parent
    return missing


def make_dir(path: Path, flag: str = "--out") -> Path:
    """``path`` created (with its parents) if absent; an :class:`OutError` naming ``flag`` when it
    is a file or cannot be created (a parent that is a file, /proc, no permission)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutError(f"{flag}: {path} is a file; pass a directory for the output")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutError(f"{flag}: cannot create the directory {path}: {exc.strerror or exc}"
                       f"{f' ({exc.filename})' if exc.filename and str(exc.filename) != str(path) else ''}; "
                       "pass a directory you can write") from None
    return path


def foreign_files(path: Path) -> list[str]:
    """What ``path`` holds besides its :data:`LOCK_FILE`, sorted (names)."""
    return sorted(p.name for p in Path(path).iterdir() if p.name != LOCK_FILE)


def claim_out(out: Path, *, resume: bool = False) -> RunLock:
    """Make ``out`` this process's run directory and return its held :class:`RunLock`: created
    if absent, locked (:class:`LockHeld` if another process holds it), then, without ``resume``,
    required to be empty (:class:`OutError` naming what it holds) — checked under the lock, so two
    processes racing for one new ``--out`` cannot both pass.  With ``resume`` the runner checks
    that it is a run directory (it must exist: a resume creates nothing)."""
    if resume and not Path(out).is_dir():
        raise OutError(f"--out: {out} is not a directory, so there is no run to --resume there; drop --resume to "
                       "start a new run")
    created = _missing_dirs(out)
    out = make_dir(out)
    if not resume and (out / LOCK_FILE).exists():
        # a run directory in use: its holder named (LockHeld), not "not empty" (the files it is writing)
        try:
            RunLock(out).acquire().release()
        except OSError:
            pass  # (a lock file that cannot be opened: the refusals below say what is there)
    if not resume:
        require_empty(out)  # before the lock file is made: a foreign directory is left untouched
    try:
        lock = RunLock(out).acquire()
    except OSError as exc:
        raise OutError(f"--out: cannot lock {out / LOCK_FILE}: {exc.strerror or exc}; pass a directory you can "
                       "write") from None
    if not resume:
        try:
            require_empty(out)  # again under the lock: another process may have won the race
        except OutError:
            lock.release()
            raise
    lock.created = created
    return lock


def require_empty(out: Path) -> None:
    """:class:`OutError` naming what ``out`` holds besides its lock file, if anything."""
    found = foreign_files(out)
    if found:
        shown = ", ".join(found[:5]) + (f" and {len(found) - 5} more" if len(found) > 5 else "")
        raise OutError(f"--out: {out} is not empty (it holds {shown}); results are never overwritten: pass a "
                       "new or empty directory, or --resume to finish an interrupted run there")
