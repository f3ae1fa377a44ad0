"""Simulated benchmarks, one folder each (`envs/libero/`).

`BENCHMARK_SUITES` names every benchmark, its suites and their sizes without importing a simulator, so
cell references, task ids and episode counts are checked while the workflow builds the DAG
(`tests/test_libero_suite.py` compares the sizes with LIBERO's own benchmark and init-state files).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from vlaquantbench.errors import UserError


@dataclass(frozen=True)
class SuiteSize:
    tasks: int  # task ids 0..tasks-1, in the benchmark's task order
    init_states: int  # official initial states per task, ids 0..init_states-1
    worker_gib: float  # memory of one simulator worker process (envs.memory), measured as noted below


BENCHMARK_SUITES = {
    "libero": {
        "libero_spatial": SuiteSize(tasks=10, init_states=50, worker_gib=2.0),
        "libero_object": SuiteSize(tasks=10, init_states=50, worker_gib=2.0),
        "libero_goal": SuiteSize(tasks=10, init_states=50, worker_gib=2.0),
        "libero_10": SuiteSize(tasks=10, init_states=50, worker_gib=2.0),
    }
}


def check_ids(field: str, ids: Iterable[int], count: int, what: str) -> None:
    """UserError `<field>: <ids outside 0..count-1> ...` naming the field, the offending ids and the range.

    `what` says what the ids index, e.g. "libero_spatial has 10 tasks"."""
    outside = sorted({i for i in ids if not 0 <= i < count})
    if outside:
        shown = ", ".join(map(str, outside[:8])) + (", ..." if len(outside) > 8 else "")
        verb = "is" if len(outside) == 1 else "are"
        raise UserError(f"{field}: {shown} {verb} outside 0..{count - 1} ({what})")
