"""Atomic file writes: a reader (or a rerun after `kill -9`) sees the old file or the whole new one.

    with atomic_write(path, "wb") as handle:
        frame.to_parquet(handle)

The data goes to a hidden temporary file beside `path`, is fsync'd, and is renamed over `path`
only when the block ends without an exception; on an exception the temporary file is removed.
"""

from __future__ import annotations

import os
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
    # pid and thread in the name: concurrent writers of one path never share a temporary file.
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{threading.get_ident()}.tmp")
    try:
        with open(tmp, mode.replace("w", "x"), **open_kwargs) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text(path: str | Path, text: str) -> Path:
    """Write `text` to `path` atomically; returns the path."""
    with atomic_write(path) as handle:
        handle.write(text)
    return Path(path)
