"""Memory: what a rollout job's simulator workers need, what this process may use, and whether a dead
worker was killed for memory.

A simulator worker is a whole interpreter with its simulator and one built env; `SuiteSize.worker_gib`
(each benchmark's declaration, `envs.registry`) holds its measured footprint. A job's worker count (`study.execution.num_envs`
or `vqb rollout --num-envs`) is checked against `available_memory()` before any worker starts: capped to
what fits, with a warning naming the setting and both numbers (an episode's seed, init state and noise
stream do not depend on how many workers run; on the CPU neither do its actions), and refused when not one
fits, or, for a calibration (per-call statistics), when fewer than asked for fit. `job_memory_mb` is what the rollout and calibrate rules declare
as `mem_mb`, so a SLURM job asks for the memory its workers need.
"""

from __future__ import annotations

import math
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from vlaquantbench.envs.registry import BENCHMARK_SUITES
from vlaquantbench.errors import UserError

GIB = 2**30
# Host memory of the policy process beside its workers. Measured: the 64-environment H200 benchmark's host
# held 3.4 GB before its workers started (benchmarks/results/closed_loop_gpu_64_mem.log); a full-size pi0.5
# on the CPU holds its float32 weights in host memory (about 14 GiB), so 16 GiB covers both.
POLICY_GIB = 16.0
# Overrides the memory reading (GiB, a number): for a site whose limit is not visible as a cgroup, and tests.
OVERRIDE = "VQB_MEMORY_AVAILABLE_GB"
# Where the kernel publishes limits and OOM kills; module attributes so that tests can point them at a
# cgroup of their own (no real cgroup can be created on the machines the tests run on).
CGROUP_ROOT = Path("/sys/fs/cgroup")
PROC_CGROUP = Path("/proc/self/cgroup")
VMSTAT = Path("/proc/vmstat")


@dataclass(frozen=True)
class Available:
    bytes: int
    source: str  # where the number comes from, in words

    def __str__(self) -> str:
        return f"{self.bytes / GIB:.1f} GiB available ({self.source})"


def worker_gib(benchmark: str, suite: str) -> float:
    return BENCHMARK_SUITES[benchmark][suite].worker_gib


def job_memory_mb(benchmark: str, suite: str, workers: int) -> int:
    """Memory a rollout or calibration job asks its scheduler for: `workers` simulator workers and the policy."""
    return math.ceil((workers * worker_gib(benchmark, suite) + POLICY_GIB) * GIB / 2**20)


def _cgroup_dirs() -> list[Path]:
    """This process's memory cgroup folders (v2 unified or v1 memory controller), innermost first: a limit
    set on any ancestor applies too. In a cgroup namespace the path is `/` and the mount is the cgroup."""
    try:
        lines = PROC_CGROUP.read_text().splitlines()
    except OSError:
        return []
    found = []
    for line in lines:
        _, controllers, path = line.split(":", 2)
        if controllers == "":
            mount = CGROUP_ROOT if (CGROUP_ROOT / "cgroup.controllers").exists() else CGROUP_ROOT / "unified"
        elif "memory" in controllers.split(","):
            mount = CGROUP_ROOT / "memory"
        else:
            continue
        folder = mount / path.lstrip("/")
        while folder != mount.parent and folder.is_relative_to(mount):
            if folder.is_dir():
                found.append(folder)
            folder = folder.parent
    return found


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None  # v2 writes "max" for no limit


def _cgroup_available() -> Available | None:
    """The tightest cgroup limit less the cgroup's use: v2 `memory.max` - `memory.current`, v1
    `memory.limit_in_bytes` - `memory.usage_in_bytes` (v1 writes a huge number for no limit).
    Hand-written: psutil reads /proc/meminfo, which ignores cgroup limits."""
    tightest = None
    for folder in _cgroup_dirs():
        for limit_file, usage_file in (("memory.max", "memory.current"), ("memory.limit_in_bytes", "memory.usage_in_bytes")):
            limit, usage = _read_int(folder / limit_file), _read_int(folder / usage_file)
            if limit is None or usage is None or limit >= 2**60:
                continue
            left = Available(max(0, limit - usage), f"cgroup {folder / limit_file} {limit / GIB:.1f} GiB less "
                                                    f"{usage / GIB:.1f} GiB in use")
            if tightest is None or left.bytes < tightest.bytes:
                tightest = left
    return tightest


def available_memory() -> Available:
    """The memory new processes of this job may use: the tighter of the cgroup's limit less its use and the
    kernel's MemAvailable (/proc/meminfo), or the `VQB_MEMORY_AVAILABLE_GB` override."""
    if OVERRIDE in os.environ:
        value = os.environ[OVERRIDE]
        try:
            gib = float(value)
        except ValueError:
            raise UserError(f"{OVERRIDE}={value!r} is not a number of GiB") from None
        return Available(int(gib * GIB), f"{OVERRIDE}={value}")
    import psutil

    meminfo = Available(psutil.virtual_memory().available, "MemAvailable of /proc/meminfo")
    cgroup = _cgroup_available()
    return cgroup if cgroup is not None and cgroup.bytes < meminfo.bytes else meminfo


def affordable_workers(requested: int, benchmark: str, suite: str, setting: str, cap: bool = True) -> int:
    """`requested` workers, or as many as the available memory holds (with a warning naming `setting` and both
    numbers); UserError when not one worker fits, or when `cap` is False and fewer than `requested` fit."""
    each = worker_gib(benchmark, suite)
    available = available_memory()
    fits = int(available.bytes / GIB // each)
    if fits >= requested:
        return requested
    need = f"{requested} {benchmark} workers x {each} GiB on {suite} = {requested * each:.1f} GiB"
    if fits < 1 or not cap:
        remedy = "not one worker fits" if fits < 1 else f"set it to at most {fits} or give the job more memory"
        raise UserError(f"{setting} = {requested}: {need}, but {available}: {remedy}")
    print(f"warning: {setting} = {requested}: {need}, but {available}; running {fits} workers instead "
          "(each episode keeps its seed, init state and noise stream)", file=sys.stderr)
    return fits


def oom_kill_counts() -> dict[str, int]:
    """The kernel's out-of-memory kill counters this process can read: its cgroups' (v2 `memory.events`,
    v1 `memory.oom_control`) and the machine's (`/proc/vmstat`), by file."""
    files = [folder / name for folder in _cgroup_dirs() for name in ("memory.events", "memory.oom_control")]
    counts = {}
    for path in [*files, VMSTAT]:
        try:
            match = re.search(r"^oom_kill (\d+)$", path.read_text(), re.MULTILINE)
        except OSError:
            continue
        if match:
            counts[str(path)] = int(match.group(1))
    return counts


def oom_kills_since(before: dict[str, int]) -> list[str]:
    """The counters of `oom_kill_counts()` that rose since `before`, as `<file> oom_kill a -> b`."""
    return [f"{path} oom_kill {before[path]} -> {count}" for path, count in oom_kill_counts().items()
            if path in before and count > before[path]]
