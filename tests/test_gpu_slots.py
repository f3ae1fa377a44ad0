"""One GPU per job on a local node (issue 36): real processes taking real flock'd slot files, and the
`profiles/local-gpus` dry run of a cuda study on this machine, which has no GPU (nvidia-smi missing, so the
device count comes from study.execution.gpus)."""

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from test_dag_slurm import SNAKEMAKE, jobs_by_rule, workflow_copy

from vlaquantbench.envs.memory import job_memory_mb
from vlaquantbench.errors import UserError
from vlaquantbench.runner.gpus import (
    TRUST_GPUS,
    Gpu,
    LocalGpuPlan,
    NoFreeGpu,
    device_files,
    device_record,
    gpu_slot,
    node_gpus,
)
from vlaquantbench.runner.journal import header_differences
from vlaquantbench.runner.provenance import host

# A job: take a slot of `gpus` devices, print which (and the CUDA_VISIBLE_DEVICES it set), hold it until killed.
HOLDER = """
import os, sys, time
from vlaquantbench.runner.gpus import Gpu, gpu_slot
with gpu_slot(sys.argv[1], [Gpu(i) for i in range(int(sys.argv[2]))], f"job {os.getpid()}", int(sys.argv[3])) as gpu:
    print(gpu.index, os.environ["CUDA_VISIBLE_DEVICES"], flush=True)
    time.sleep(600)
"""


def start_holders(slots: Path, gpus: int, count: int, per_gpu: int = 1) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", HOLDER, str(slots), str(gpus), str(per_gpu)], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True) for _ in range(count)]


def stop(procs):
    for proc in procs:
        proc.kill()
        proc.wait()


def test_concurrent_jobs_take_distinct_devices_and_a_job_beyond_them_is_refused(tmp_path):
    holders = start_holders(tmp_path / "slots", 3, 3)  # three jobs start at once, racing for the slots
    try:
        taken = [proc.stdout.readline().split() for proc in holders]
        assert sorted(int(index) for index, _ in taken) == [0, 1, 2], taken
        assert all(index == visible for index, visible in taken)  # each job sees its own device alone
        for index, _ in taken:  # each lock file names its live holder
            holder = json.loads((tmp_path / "slots" / f"{os.uname().nodename}-gpu{index}.lock").read_text())
            assert holder["pid"] in {p.pid for p in holders} and holder["gpu"]["index"] == int(index)
        fourth = start_holders(tmp_path / "slots", 3, 1)[0]
        _, err = fourth.communicate(timeout=60)
        assert fourth.returncode == 1 and "every GPU slot" in err and "--resources gpu" in err, err
        assert all(f"pid {p.pid}" in err for p in holders), err  # the refusal names the holders
    finally:
        stop(holders)


def test_jobs_sharing_devices_fill_every_device_once_before_any_twice_and_no_more(tmp_path):
    """study.execution.jobs_per_gpu 2 on two devices: four jobs at once, two on each, a fifth refused."""
    holders = start_holders(tmp_path / "slots", 2, 4, per_gpu=2)
    try:
        taken = sorted(int(proc.stdout.readline().split()[0]) for proc in holders)
        assert taken == [0, 0, 1, 1], taken
        locks = sorted(p.name for p in (tmp_path / "slots").iterdir())
        host_name = os.uname().nodename
        assert locks == sorted(f"{host_name}-gpu{i}{s}.lock" for i in (0, 1) for s in ("", "-1")), locks
        fifth = start_holders(tmp_path / "slots", 2, 1, per_gpu=2)[0]
        _, err = fifth.communicate(timeout=60)
        assert fifth.returncode == 1 and "(2 x 2)" in err and "jobs_per_gpu" in err, err
    finally:
        stop(holders)


def test_a_slot_is_free_again_after_its_holder_is_killed_with_sigkill(tmp_path):
    first = start_holders(tmp_path / "slots", 1, 1)[0]
    try:
        assert first.stdout.readline().split()[0] == "0"
        with pytest.raises(NoFreeGpu, match=f"pid {first.pid}"):  # held while its holder lives
            with gpu_slot(tmp_path / "slots", [Gpu(0)], "test"):
                pass
        os.kill(first.pid, signal.SIGKILL)
        first.wait()
        with gpu_slot(tmp_path / "slots", [Gpu(0)], "test") as gpu:  # no clean-up ran: the kernel freed it
            assert gpu.index == 0 and os.environ["CUDA_VISIBLE_DEVICES"] == "0"
    finally:
        stop([first])


def test_more_gpu_jobs_than_devices_are_refused_naming_the_setting(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))  # no nvidia-smi, on GPU machines too: the count is the config's,
    monkeypatch.setenv(TRUST_GPUS, "1")  # taken on trust (a node planning the jobs of others)
    with pytest.raises(UserError, match=r"--resources gpu=4 asks for 4 GPU jobs at once but this node has 2 GPU"):
        LocalGpuPlan.for_node(2, 4, cores=16)
    with pytest.raises(UserError, match=r"study\.execution\.gpus where nvidia-smi is missing"):
        LocalGpuPlan.for_node(None, None, cores=16)
    plan = LocalGpuPlan.for_node(4, None, cores=64)  # --resources gpu unset: one job per device
    assert (plan.jobs, plan.threads, plan.workers(8), plan.workers(64)) == (4, 16, 8, 15)
    assert node_gpus(2)[0] == [Gpu(0), Gpu(1)]
    plan = LocalGpuPlan.for_node(1, None, cores=16, per_gpu=3)  # one device shared by three jobs
    assert (plan.jobs, plan.threads, plan.workers(16)) == (3, 5, 4)
    assert "one of a device's 3 slots" in plan.describe(16)
    with pytest.raises(UserError, match=r"--resources gpu=4 .* 1 GPU\(s\) .* taking 3 job\(s\) each"):
        LocalGpuPlan.for_node(1, 4, cores=16, per_gpu=3)


def dry_run(checkout: Path, *args: str, gpus: int | None, trusted: bool = True) -> subprocess.CompletedProcess:
    # A PATH without nvidia-smi, on GPU machines too: Python's and the one tool Snakemake calls (`which`).
    tools = checkout / "tools"
    if not tools.exists():
        tools.mkdir()
        (tools / "which").symlink_to(shutil.which("which"))
    (checkout / "gpus.yaml").write_text(yaml.safe_dump({"study": {"execution": {"gpus": gpus}}}))
    return subprocess.run(
        [*SNAKEMAKE, "--profile", "profiles/local-gpus", "--configfile", "config/paper.yaml", "gpus.yaml", "-n", *args],
        cwd=checkout, capture_output=True, text=True, timeout=600,
        env={**{k: v for k, v in os.environ.items() if k != TRUST_GPUS}, "PATH": f"{Path(sys.executable).parent}:{tools}",
             **({TRUST_GPUS: "1"} if trusted else {})},
    )


def test_local_gpus_profile_dry_run_states_the_plan_on_a_machine_without_gpus(tmp_path):
    checkout = workflow_copy(tmp_path)
    result = dry_run(checkout, "--cores", "8", gpus=2)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-3000:]
    assert "Using profile profiles/local-gpus" in output
    assert ("local GPUs (study.execution.gpus: 2 (nvidia-smi not found: taken on trust, VQB_TRUST_GPUS=1)): 0, 1; at most 2 "
            "rollout/calibrate jobs at once (--resources gpu=2), each on a device of its own") in output
    assert "each with 4 of 8 cores and 3 simulator worker(s) (study.execution.num_envs: 8)" in output
    jobs = jobs_by_rule(output)
    assert len(jobs["rollout"]) == 22 and len(jobs["calibrate"]) == 1
    for resources in jobs["rollout"]:  # memory for the 3 workers a job starts, not the config's 8
        assert f"gpu=1, mem_mb={job_memory_mb('libero', 'libero_spatial', 3)}," in resources, resources
    assert "gpu=1" in jobs["calibrate"][0]
    assert output.count("threads: 4") == 22 + 1  # the GPU jobs' share of the cores
    assert not (checkout / "results" / "cells").exists()

    refused = dry_run(checkout, "--cores", "4", "--resources", "gpu=3", gpus=2)
    assert refused.returncode != 0
    assert "--resources gpu=3 asks for 3 GPU jobs at once but this node has 2 GPU(s)" in refused.stdout, refused.stdout[-3000:]
    # Neither nvidia-smi nor study.execution.gpus: the dry run plans the jobs and says that a real run stops.
    no_gpu = dry_run(checkout, "--cores", "4", gpus=None)
    assert no_gpu.returncode == 0 and "set study.execution.gpus where nvidia-smi is missing" in no_gpu.stderr
    assert "a real run stops here" in no_gpu.stderr and len(jobs_by_rule(no_gpu.stdout + no_gpu.stderr)["rollout"]) == 22


def test_more_gpus_than_the_node_has_are_refused_while_the_dag_is_built_naming_the_override(tmp_path):
    """Without nvidia-smi, study.execution.gpus is checked against the node's /dev/nvidia<N> files (none here),
    in a dry run too: before, each job died in torch ("Found no NVIDIA driver")."""
    checkout = workflow_copy(tmp_path)
    asked = len(device_files()) + 1
    refused = dry_run(checkout, "--cores", "4", gpus=asked, trusted=False)
    output = refused.stdout + refused.stderr
    assert refused.returncode != 0
    assert (f"study.execution.gpus: {asked} asks for more GPUs than this node has: nvidia-smi is missing and /dev holds "
            f"{asked - 1} GPU device file(s)") in output, output[-3000:]
    assert ("Where the jobs run on other nodes (a cluster whose login node has no GPU), submit them through the "
            "cluster's executor (--profile profiles/slurm), or set VQB_TRUST_GPUS=1 to take the setting on trust") in output
    assert not (checkout / "results").exists()


def test_the_header_names_no_device_on_the_cpu_and_a_cell_resumes_on_another_gpu_of_its_model():
    assert device_record("cpu") is None  # CPU headers are as they were: their journals resume
    base = {"model": "pi05", "config": {}}
    h200 = {"index": 0, "name": "NVIDIA H200", "uuid": "GPU-aaaa"}
    other_h200 = {"index": 3, "name": "NVIDIA H200", "uuid": "GPU-bbbb"}
    assert header_differences({**base, "device": h200}, {**base, "device": other_h200}) == []
    assert header_differences(base, {**base, "device": other_h200}) == []  # a journal from before headers named it
    h100 = {"index": 0, "name": "NVIDIA H100 80GB HBM3", "uuid": "GPU-cccc"}
    assert header_differences({**base, "device": h200}, {**base, "device": h100}) == [
        'device: recorded={"name": "NVIDIA H200"} current={"name": "NVIDIA H100 80GB HBM3"}']


def test_the_header_names_the_host_and_a_cell_resumes_only_on_its_cpu_and_renderer():
    """`host`: the CPU model and torch's instruction set, MuJoCo's rendering backend and the listed GPUs. A
    journal resumes on a node listing other GPUs, not on another CPU or renderer (both move closed-loop
    outcomes), and a journal from before headers named the host resumes."""
    here = host()
    cpuinfo = Path("/proc/cpuinfo").read_text()
    assert here["cpu"] and f"model name\t: {here['cpu']}" in cpuinfo
    assert here["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert here["mujoco_gl"] == os.environ.get("MUJOCO_GL", "egl")
    if shutil.which("nvidia-smi") is None:
        assert here["gpus"] == []
    base = {"model": "pi05", "config": {}}
    xeon = {"cpu": "Intel(R) Xeon(R) Platinum 8480+", "cpu_capability": "AVX512", "mujoco_gl": "egl", "gpus": ["NVIDIA H200"]}
    assert header_differences({**base, "host": xeon}, {**base, "host": {**xeon, "gpus": ["NVIDIA H200"] * 8}}) == []
    assert header_differences(base, {**base, "host": here}) == []
    assert header_differences({**base, "host": xeon}, {**base, "host": {**xeon, "cpu": here["cpu"]}}) == [
        f'host: recorded={json.dumps({k: v for k, v in xeon.items() if k != "gpus"})} '
        f'current={json.dumps({**{k: v for k, v in xeon.items() if k != "gpus"}, "cpu": here["cpu"]})}']
    assert header_differences({**base, "host": xeon}, {**base, "host": {**xeon, "mujoco_gl": "osmesa"}})
