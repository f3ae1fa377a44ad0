"""SIGTERM handled as Ctrl-C is: SLURM sends it at a job's time limit and on preemption, `kill` by
default. Raised as `Terminated`, a KeyboardInterrupt, every cleanup that runs on Ctrl-C runs for it
too: the simulator workers are closed, the journal is left whole, and `vqb rollout` says how far the
cell got and how to resume it before it exits 128 + 15.
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from vlaquantbench.cells import CellConfig


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived; `signum` gives the conventional exit status 128 + signum."""

    signum = signal.SIGTERM


@contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """While inside, SIGTERM raises Terminated in the main thread (once: a second SIGTERM during the
    cleanup is ignored, so that the workers are still closed; SIGKILL remains).

    A SIGTERM that the process was started with ignored, or that someone else handles, is left as it
    is: a parent that ignores a signal for its children means it (as a shell does with SIGINT for a
    background job, which e6e0a57 learned the hard way)."""
    if signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return

    def terminate(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        raise Terminated()

    signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def report_stop(stop: KeyboardInterrupt, cfg: CellConfig, out: str | Path, journal: str | Path) -> int:
    """Say on stderr how far cell `cfg` got (its episodes recorded in `journal`) and how to resume it,
    after Ctrl-C or SIGTERM (`stop`); the conventional exit status, 128 + the signal's number."""
    from vlaquantbench.runner.journal import recorded_episodes

    signum = getattr(stop, "signum", signal.SIGINT)
    what = "interrupted" if signum == signal.SIGINT else f"terminated ({signal.Signals(signum).name})"
    total = len(cfg.tasks) * cfg.episodes_per_task
    print(f"\nvqb rollout: {what}: {cfg.ref} has {recorded_episodes(Path(journal))} of {total} episodes "
          f"recorded in {out}; run the same command again to resume it", file=sys.stderr, flush=True)
    return 128 + signum
