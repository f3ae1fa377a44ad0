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


# worker_gib: the largest proportional set size (PSS, psutil's memory_full_info; shared libraries counted once
# across workers) of a LIBERO worker (camera 256, MuJoCo 3.3.2, MUJOCO_GL=egl) after an episode reset and a
# 10-action chunk, measured on the 2-core x86-64 development machine (2026-12-04): fresh workers on every task
# of the suite, and one worker that built each task in turn (rebuilding leaves up to 0.5 GiB behind: LIBERO-10
# task 4 holds 2.35 GiB fresh, 2.86 after the other nine), rounded up to 0.1 GiB. Spatial, Object, Goal, 10: fresh
# maxima 1.80, 1.94, 1.53, 2.35 GiB; after the cycle 1.85, 2.10, 1.68, 2.86. An idle worker interpreter holds 0.1 GiB. The
# 64-worker H200 benchmark's host held about 1.7 GB per worker (benchmarks/results/closed_loop_gpu_64_mem.log).
BENCHMARK_SUITES = {
    "libero": {
        "libero_spatial": SuiteSize(tasks=10, init_states=50, worker_gib=1.9),
        "libero_object": SuiteSize(tasks=10, init_states=50, worker_gib=2.1),
        "libero_goal": SuiteSize(tasks=10, init_states=50, worker_gib=1.7),
        "libero_10": SuiteSize(tasks=10, init_states=50, worker_gib=2.9),
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
