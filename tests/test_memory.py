"""Issue 35 item 5: a job's LIBERO workers against the memory available, and a worker killed for memory
reported as such only on the kernel's record (`vlaquantbench.envs.memory`)."""

import math
import os
import signal
import subprocess
import sys

import pytest

from vlaquantbench.envs import memory
from vlaquantbench.envs.memory import GIB, affordable_workers, available_memory, job_memory_mb, oom_kill_counts, worker_gib
from vlaquantbench.errors import UserError
from paths import ROOT

SPATIAL = worker_gib("libero", "libero_spatial")


def mem_available() -> int:
    for line in open("/proc/meminfo"):
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("/proc/meminfo has no MemAvailable")


def test_the_memory_available_is_read_from_proc_meminfo_and_the_real_cgroup(monkeypatch):
    monkeypatch.delenv(memory.OVERRIDE, raising=False)
    before, available, after = mem_available(), available_memory(), mem_available()
    # This machine's cgroup has no limit (v1 writes a huge number, v2 "max"): MemAvailable is the reading.
    assert memory._cgroup_available() is None or memory._cgroup_available().bytes < before
    if memory._cgroup_available() is None:
        assert available.source == "MemAvailable of /proc/meminfo"
        assert min(before, after) - 256 * 2**20 <= available.bytes <= max(before, after) + 256 * 2**20
    counts = oom_kill_counts()  # the kernel's real counters, as a dead worker's report reads them
    vmstat = dict(line.split() for line in open("/proc/vmstat"))
    assert counts["/proc/vmstat"] >= 0 and int(vmstat["oom_kill"]) >= counts["/proc/vmstat"]


@pytest.mark.parametrize("version", ["v2", "v1"])
def test_a_cgroup_limit_is_the_limit_less_its_use(tmp_path, monkeypatch, version):
    # No cgroup can be created here: a cgroup tree of files laid out as the kernel lays them out.
    monkeypatch.delenv(memory.OVERRIDE, raising=False)
    if version == "v2":
        (tmp_path / "proc_cgroup").write_text("0::/job_7/step_0\n")
        leaf, parent = tmp_path / "job_7/step_0", tmp_path / "job_7"
        files = ("memory.max", "memory.current")
        (tmp_path / "cgroup.controllers").write_text("memory\n")
        unlimited = "max"
    else:
        (tmp_path / "proc_cgroup").write_text("4:memory:/slurm/job_7\n0::/\n")
        leaf, parent = tmp_path / "memory/slurm/job_7", tmp_path / "memory/slurm"
        files = ("memory.limit_in_bytes", "memory.usage_in_bytes")
        unlimited = str(2**63 - 4096)
    leaf.mkdir(parents=True)
    (leaf / files[0]).write_text(unlimited + "\n")  # the step has none; its job (an ancestor) has one
    (leaf / files[1]).write_text(f"{1 * GIB}\n")
    (parent / files[0]).write_text(f"{8 * GIB}\n")
    (parent / files[1]).write_text(f"{3 * GIB}\n")
    monkeypatch.setattr(memory, "CGROUP_ROOT", tmp_path)
    monkeypatch.setattr(memory, "PROC_CGROUP", tmp_path / "proc_cgroup")
    available = available_memory()
    assert available.bytes == 5 * GIB
    assert str(available) == f"5.0 GiB available (cgroup {parent / files[0]} 8.0 GiB less 3.0 GiB in use)"


def test_a_worker_count_beyond_the_memory_is_capped_or_refused_naming_both(monkeypatch, capsys):
    monkeypatch.setenv(memory.OVERRIDE, str(3.5 * SPATIAL))
    assert affordable_workers(2, "libero", "libero_spatial", "study.execution.num_envs") == 2
    assert capsys.readouterr().err == ""
    assert affordable_workers(8, "libero", "libero_spatial", "study.execution.num_envs") == 3
    assert capsys.readouterr().err == (
        f"warning: study.execution.num_envs = 8: 8 libero workers x {SPATIAL} GiB on libero_spatial = "
        f"{8 * SPATIAL:.1f} GiB, but {3.5 * SPATIAL:.1f} GiB available ({memory.OVERRIDE}={3.5 * SPATIAL}); running 3 "
        "workers instead (each episode keeps its seed, init state and noise stream)\n")
    with pytest.raises(UserError, match=r"^study.execution.num_envs = 8: .* set it to at most 3 or give the job more memory"):
        affordable_workers(8, "libero", "libero_spatial", "study.execution.num_envs", cap=False)  # calibration
    monkeypatch.setenv(memory.OVERRIDE, "1")
    with pytest.raises(UserError, match=rf"^--num-envs = 4: 4 libero workers x {SPATIAL} GiB .* but 1.0 GiB available "
                                        rf"\({memory.OVERRIDE}=1\): not one worker fits"):
        affordable_workers(4, "libero", "libero_spatial", "--num-envs")


def test_vqb_rollout_refuses_workers_that_do_not_fit_before_the_checkpoint_download(tmp_path):
    env = {**os.environ, memory.OVERRIDE: "1"}
    cmd = [sys.executable, "-m", "vlaquantbench.cli", "rollout", "libero/libero_spatial/pi05/rtn-W4A4-ah",
           "--num-envs", "4", "--results", str(tmp_path / "out")]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=ROOT, env=env)
    assert result.returncode == 2, result.stderr
    assert (f"vqb rollout: error: --num-envs = 4: 4 libero workers x {SPATIAL} GiB on libero_spatial = "
            f"{4 * SPATIAL:.1f} GiB, but 1.0 GiB available") in result.stderr, result.stderr
    assert not (tmp_path / "out").exists()  # no checkpoint stamp, no cell folder


def test_a_job_asks_for_its_workers_memory():
    assert job_memory_mb("libero", "libero_spatial", 8) == math.ceil((8 * SPATIAL + memory.POLICY_GIB) * 1024)
    assert job_memory_mb("libero", "libero_spatial", 64) > 64 * SPATIAL * 1024


@pytest.mark.slow
def test_a_worker_killed_by_sigkill_is_said_to_be_out_of_memory_only_on_the_kernels_record(tmp_path, monkeypatch):
    from vlaquantbench.envs.libero import LiberoSuite, LiberoVectorEnv, LiberoWorkerError

    # The kernel's counters, in files this test can raise (a real OOM kill would endanger the shared machine).
    events = tmp_path / "memory.events"
    events.write_text("low 0\nhigh 0\nmax 0\noom 0\noom_kill 0\n")
    (tmp_path / "proc_cgroup").write_text("0::/\n")
    (tmp_path / "cgroup.controllers").write_text("memory\n")
    monkeypatch.setattr(memory, "CGROUP_ROOT", tmp_path)
    monkeypatch.setattr(memory, "PROC_CGROUP", tmp_path / "proc_cgroup")
    monkeypatch.setenv(memory.OVERRIDE, "3")
    suite = LiberoSuite("libero_spatial")
    with LiberoVectorEnv(suite, num_envs=1, camera_size=64) as env:
        os.kill(env.worker_pids[0], signal.SIGKILL)  # as `kill -9` or a scheduler would: no OOM recorded
        with pytest.raises(LiberoWorkerError) as failure:
            env.preload([0])
        assert (f"slot 0 failed to load:\nthe worker died; killed by SIGKILL (exit code -9); no out-of-memory kill was "
                f"recorded ({events}, /proc/vmstat), so not by the kernel's OOM killer") in str(failure.value)
        env.submit_reset(0, suite.episode_spec(0, 0))  # a new worker; the kernel now records an OOM kill
        events.write_text("low 0\nhigh 0\nmax 3\noom 1\noom_kill 1\n")
        os.kill(env.worker_pids[0], signal.SIGKILL)
        with pytest.raises(LiberoWorkerError) as failure:
            env.collect()
        assert (f"the worker died; killed by SIGKILL, likely out of memory: 1 workers x {SPATIAL} GiB vs 3.0 GiB "
                f"available ({memory.OVERRIDE}=3) when they started; the kernel killed for memory since "
                f"({events} oom_kill 0 -> 1)") in str(failure.value)
