"""One writer per cell: an exclusive lock on the cell's folder (and on its journal when that lives
elsewhere), held while a process writes the cell, so that a second writer is refused by name
instead of running every episode a second time into the same journal.

The lock is `fcntl.flock` on a lock file (`writer.lock` in the cell's folder, `<journal>.lock`
beside a journal kept elsewhere). The kernel releases it when its holder exits in any way, kill -9
included, so a lock is never stale and nothing has to be cleaned up; the file itself stays (removing
it would race with the next writer's open). While held, the file names its holder (pid, host,
start time, cell) for the refusal. The `filelock` package is not used: its flock lock keeps no
record of its holder (its `pid` reads only its soft-lock fallback's marker), and the holder's name
is what the refusal must give.

NFS (a results folder shared by SLURM jobs on several nodes): Linux implements flock on NFS as a
whole-file POSIX lock that the server arbitrates between hosts, so two jobs on two nodes exclude each
other, unless the file system is mounted with `nolock` or `local_lock=flock`/`all`, where each host
sees only its own locks. A node that crashes holding a lock keeps it until the server's lease for
that node expires (NFSv4: about 90 s).
"""

from __future__ import annotations

import datetime
import fcntl
import json
import os
import socket
import sys
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

from vlaquantbench.errors import UserError

LOCK_FILE = "writer.lock"


class CellLocked(UserError):
    """Another process writes this cell; its lock file names it."""


# Locks this process holds: lock file -> (descriptor, depth). flock locks belong to an open file
# description, so a second open of the same file in this process would refuse this process itself;
# `vqb rollout` takes the lock before the download and calibration, and `run_cell` takes it again.
_held: dict[Path, list[int]] = {}


def lock_files(out_dir: str | Path, journal: str | Path) -> list[Path]:
    """The lock files of a cell written to `out_dir` with its journal at `journal`."""
    out_dir, journal = Path(out_dir), Path(journal)
    files = [out_dir / LOCK_FILE]
    if journal.parent.absolute() != out_dir.absolute():
        files.append(journal.with_name(journal.name + ".lock"))
    return files


@contextmanager
def writing(out_dir: str | Path, journal: str | Path, cell: str) -> Iterator[None]:
    """Hold the cell's writer locks, or raise CellLocked naming the process that holds one."""
    with ExitStack() as stack:
        for path in lock_files(out_dir, journal):
            stack.enter_context(_exclusive(path, cell))
        yield


@contextmanager
def _exclusive(path: Path, cell: str) -> Iterator[None]:
    path = path.absolute()
    if path in _held:
        _held[path][1] += 1
    else:
        fd = try_flock(path, holder(cell=cell))
        if isinstance(fd, str):
            raise CellLocked(_refusal(path, cell, fd))
        _held[path] = [fd, 1]
    try:
        yield
    finally:
        _held[path][1] -= 1
        if not _held[path][1]:
            release_flock(_held.pop(path)[0])


def try_flock(path: Path, holder: dict) -> int | str:
    """An exclusive flock on `path`, which then names `holder`: its descriptor, or, when another process
    holds the lock, the text that process wrote into the file (empty while it has not written yet)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)  # not O_TRUNC: a refused process reads the holder
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        text = os.pread(fd, 4096, 0).decode(errors="replace")
        os.close(fd)
        return text
    except BaseException:
        os.close(fd)
        raise
    os.ftruncate(fd, 0)
    os.pwrite(fd, (json.dumps(holder, sort_keys=True) + "\n").encode(), 0)
    return fd


def release_flock(fd: int) -> None:
    os.ftruncate(fd, 0)  # the next reader of an unheld lock file finds no stale holder
    os.close(fd)  # releases the lock


def holder(**what) -> dict:
    """What a lock file says of its holder: this process, and `what` it holds the lock for."""
    return {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join(sys.argv),
        **what,
    }


def _refusal(path: Path, cell: str, holder: str) -> str:
    try:
        who = json.loads(holder)
        named = (f"pid {who['pid']} on host {who['host']}, started {who['started']}, writing cell {who['cell']} "
                 f"(command: {who['command']})")
    except (ValueError, KeyError, TypeError):  # the holder is between its lock and its write
        named = "a process that has not named itself yet"
    return (f"cell {cell}: another process writes it: {path} is locked by {named}. Two writers would run every "
            "episode twice: wait for that run to end, or stop it (its lock ends with it, even on kill -9) and run "
            "this again, which resumes the cell from its journal.")
