"""Atomic file writes: a reader (or a rerun after `kill -9`) sees the old file or the whole new one.

    with atomic_write(path, "wb") as handle:
        frame.to_parquet(handle)

The data goes to a hidden temporary file beside `path`, is fsync'd, and is renamed over `path`
only when the block ends without an exception; on an exception the temporary file is removed. A
writer killed outright (`kill -9`) leaves its temporary file behind: the next write of `path` on the
same host removes the ones whose process is gone.
"""

from __future__ import annotations

import glob
import os
import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO


@contextmanager
def atomic_write(path: str | Path, mode: str = "w", **open_kwargs) -> Iterator[IO]:
    """An open handle (`mode` "w" or "wb") whose contents replace `path` when the block succeeds."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write writes whole files (mode 'w' or 'wb'), not mode {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_leftovers(path)
    # host, pid and thread in the name: concurrent writers of one path never share a temporary file.
    tmp = path.with_name(f"{_prefix(path)}{os.getpid()}-{threading.get_ident()}.tmp")
    try:
        with open(tmp, mode.replace("w", "x"), **open_kwargs) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _prefix(path: Path) -> str:
    return f".{path.name}.{socket.gethostname()}."


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_leftovers(path: str | Path) -> list[Path]:
    """Remove the temporary files of `path` left by writers on this host whose process has died;
    returns them. Another host's (a shared file system) are kept: their pids mean nothing here."""
    path = Path(path)
    prefix = _prefix(path)
    removed = []
    for tmp in path.parent.glob(glob.escape(prefix) + "*-*.tmp"):
        pid = tmp.name[len(prefix):].split("-", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    return removed


def write_text(path: str | Path, text: str) -> Path:
    """Write `text` to `path` atomically; returns the path."""
    with atomic_write(path) as handle:
        handle.write(text)
    return Path(path)
