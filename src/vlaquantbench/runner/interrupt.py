"""Ctrl-C that a running cell cannot lose.

Python raises `KeyboardInterrupt` wherever the main thread is when SIGINT arrives. Raised inside a
finalizer (a `__del__` or `weakref.finalize` callback that garbage collection happens to run then),
it is printed as "Exception ignored in ..." and dropped, and the cell runs on as if no key had been
pressed (a CI run saw `vqb rollout` finish its cell with exit 0 after Ctrl-C). While a cell runs,
SIGINT is also recorded, and the episode loop raises it again at the next episode it records.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

_received = threading.Event()


def _record_and_raise(signum, frame):
    _received.set()
    raise KeyboardInterrupt


@contextlib.contextmanager
def sigint_recorded() -> Iterator[None]:
    """Record SIGINT for `raise_if_interrupted` while the block runs (in the main thread, where
    Python runs signal handlers; elsewhere nothing changes). The previous handler comes back after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _received.clear()
    previous = signal.signal(signal.SIGINT, _record_and_raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _received.clear()


def raise_if_interrupted() -> None:
    """`KeyboardInterrupt` if SIGINT arrived in the running `sigint_recorded` block, whether or not
    it was raised then."""
    if _received.is_set():
        raise KeyboardInterrupt
