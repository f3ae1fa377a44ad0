"""One GPU per job on a node with several, when Snakemake runs the jobs locally (no SLURM).

Snakemake 9 counts a `gpu` resource (`--resources gpu=N` bounds how many GPU jobs run at once) but
assigns no device to a job: every job would run on CUDA's default device. So each rollout and
calibrate job takes a slot here before torch initialises CUDA and sets `CUDA_VISIBLE_DEVICES` to it:

- The slots are the node's devices as `nvidia-smi -L` lists them (within a `CUDA_VISIBLE_DEVICES`
  the run itself was given), or, where nvidia-smi is missing, `study.execution.gpus` devices 0..N-1,
  provided the node has that many device files `/dev/nvidia<N>` (a container without the tool); more
  is refused while the DAG is built, unless `VQB_TRUST_GPUS=1` says the jobs run on other nodes
  (a cluster login node without a GPU). `study.execution.gpus` below the listed count uses the first N.
- A slot is an exclusive `fcntl.flock` on one lock file per device in the run's slot folder
  (`.snakemake/gpu-slots`), taken as `runner.lock` takes a cell's writer lock: the kernel drops it
  when its holder exits in any way, kill -9 included, so a slot is never stale and never held by two
  live processes. The file is named by the device's UUID where known (unique across nodes, so a slot
  folder on a shared file system serves several nodes), else by host and index.
- A job that finds every slot held is refused, not queued: within one Snakemake the `gpu` resource
  (set to the device count by the workflow, or refused at start-up when `--resources gpu` asks for
  more) already keeps the GPU jobs at most one per device, so a full pool means that another process
  holds devices this run was told it has, and waiting would hide that. The refusal names the setting
  and every holder.

CUDA enumerates devices fastest first unless CUDA_DEVICE_ORDER=PCI_BUS_ID, nvidia-smi in PCI order, so
a slot is made visible by UUID, never by index, wherever the UUID is known.
"""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

from vlaquantbench.errors import UserError
from vlaquantbench.runner.lock import holder, release_flock, try_flock

SLOTS_DIR = ".snakemake/gpu-slots"
GPUS_SETTING = "study.execution.gpus"
PER_GPU_SETTING = "study.execution.jobs_per_gpu"
# Set to 1: take study.execution.gpus on trust where nvidia-smi is missing (the node that builds the DAG is not
# the one the jobs run on).
TRUST_GPUS = "VQB_TRUST_GPUS"
_DEVICE_FILE = re.compile(r"^nvidia(\d+)$")
# `GPU 0: NVIDIA H200 (UUID: GPU-0f6c...)`, one line per device (MIG instances, indented, are not listed).
_SMI_LINE = re.compile(r"^GPU (\d+): (.+) \(UUID: (GPU-[0-9a-fA-F-]+)\)$")


class NoGpu(UserError):
    """The study runs on cuda and the node has no GPU to give its jobs."""


class NoFreeGpu(UserError):
    """Every GPU slot of the node is held by another live process."""


@dataclass(frozen=True)
class Gpu:
    index: int  # nvidia-smi's index (PCI order)
    name: str | None = None
    uuid: str | None = None

    def visible(self) -> str:
        """The value of CUDA_VISIBLE_DEVICES that shows this device alone."""
        return self.uuid or str(self.index)

    def lock_name(self, share: int = 0) -> str:
        """The slot file of the device's `share`-th concurrent job (study.execution.jobs_per_gpu)."""
        name = self.uuid if self.uuid else f"{socket.gethostname()}-gpu{self.index}"
        return f"{name}-{share}.lock" if share else f"{name}.lock"


def listed_gpus() -> list[Gpu] | None:
    """The devices `nvidia-smi -L` lists, within CUDA_VISIBLE_DEVICES if set; None without nvidia-smi."""
    try:
        listing = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, check=True, timeout=60).stdout
    except (OSError, subprocess.SubprocessError):  # no driver, no binary: not a GPU node as far as we can tell
        return None
    gpus = [Gpu(int(m[1]), m[2], m[3]) for m in map(_SMI_LINE.match, listing.splitlines()) if m]
    # Indices there count in CUDA's order, fastest first: nvidia-smi's PCI order on a node of one GPU model.
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is None:
        return gpus
    wanted = [v.strip() for v in visible.split(",") if v.strip()]
    return [g for g in gpus if str(g.index) in wanted or any(g.uuid.startswith(w) for w in wanted if w.startswith("GPU-"))]


def device_files(dev: Path = Path("/dev")) -> list[str]:
    """The NVIDIA device files of this node (`/dev/nvidia0`, ...): its GPUs where nvidia-smi is missing."""
    return sorted((str(path) for path in dev.glob("nvidia*") if _DEVICE_FILE.match(path.name)),
                  key=lambda name: int(_DEVICE_FILE.match(Path(name).name)[1]))


def node_gpus(configured: int | None) -> tuple[list[Gpu], str]:
    """The node's GPU slots for `configured` (study.execution.gpus; None: every listed device), and where
    they come from in words; UserError naming the setting when it asks for more devices than are listed."""
    listed = listed_gpus()
    if listed is None:
        if configured is None:
            return [], "nvidia-smi not found and study.execution.gpus unset"
        if os.environ.get(TRUST_GPUS) == "1":
            return [Gpu(i) for i in range(configured)], f"{GPUS_SETTING}: {configured} (nvidia-smi not found: taken on trust, {TRUST_GPUS}=1)"
        found = device_files()
        if configured > len(found):
            raise UserError(f"{GPUS_SETTING}: {configured} asks for more GPUs than this node has: nvidia-smi is missing and "
                            f"/dev holds {len(found)} GPU device file(s) ({', '.join(found) or 'none'}); "
                            + (f"set it to at most {len(found)}, or " if found else "")
                            + "run on the CPU (study.runner.device: cpu). Where the jobs run on "
                            "other nodes (a cluster whose login node has no GPU), submit them through the cluster's "
                            f"executor (--profile profiles/slurm), or set {TRUST_GPUS}=1 to take the setting on trust")
        return [Gpu(i) for i in range(configured)], f"{GPUS_SETTING}: {configured} (nvidia-smi not found; /dev holds {len(found)})"
    if configured is None:
        return listed, f"nvidia-smi -L lists {len(listed)}"
    if configured > len(listed):
        raise UserError(f"{GPUS_SETTING}: {configured} asks for more GPUs than this node has: nvidia-smi -L lists "
                        f"{len(listed)} ({', '.join(g.visible() for g in listed) or 'none'}); set it to at most {len(listed)}")
    return listed[:configured], f"{GPUS_SETTING}: {configured} of the {len(listed)} nvidia-smi -L lists"


def check_gpu_jobs(requested: int | None, gpus: list[Gpu], source: str, per_gpu: int = 1) -> int:
    """How many GPU jobs may run at once: `--resources gpu` (`requested`), or `per_gpu` per device when unset
    (study.execution.jobs_per_gpu); UserError naming `--resources gpu` when it asks for more concurrent GPU jobs
    than the devices take."""
    if not gpus:
        raise NoGpu(f"the study's runner.device is cuda but this node has no GPU to give its jobs ({source}); "
                        f"set {GPUS_SETTING} where nvidia-smi is missing, or run on the CPU (study.runner.device: cpu)")
    slots = len(gpus) * per_gpu
    if requested is not None and requested > slots:
        raise UserError(f"--resources gpu={requested} asks for {requested} GPU jobs at once but this node has "
                        f"{len(gpus)} GPU(s) ({source}) taking {per_gpu} job(s) each ({PER_GPU_SETTING}); "
                        f"set --resources gpu={slots} or fewer (or leave it out: the workflow sets it to {slots}), "
                        f"or raise {PER_GPU_SETTING} where a device has room for more jobs")
    return slots if requested is None else requested


@contextmanager
def gpu_slot(slots_dir: str | Path, gpus: list[Gpu], job: str, per_gpu: int = 1) -> Iterator[Gpu]:
    """Hold one of the `per_gpu` slots of a device of `gpus` that no other live process holds (every device's
    first slot before any second one), with CUDA_VISIBLE_DEVICES set to that device alone (before torch
    initialises CUDA, which reads it once); NoFreeGpu naming every holder if none is free."""
    slots_dir = Path(slots_dir)
    held = []
    for share, gpu in ((share, gpu) for share in range(per_gpu) for gpu in gpus):
        fd = try_flock(slots_dir / gpu.lock_name(share), holder(job=job, gpu=asdict(gpu), share=share))
        if isinstance(fd, int):
            break
        held.append(f"{gpu.visible()}" + (f" (slot {share})" if per_gpu > 1 else "") + f" by {_holder_words(fd)}")
    else:
        raise NoFreeGpu(f"{job}: every GPU slot in {slots_dir} is held ({'; '.join(held) or 'no GPU given'}): more GPU "
                        f"jobs run than the devices take ({len(gpus)} x {per_gpu}); lower --resources gpu (or "
                        f"{GPUS_SETTING}, {PER_GPU_SETTING}) to the slots this run may use, or wait for the other run to end")
    previous = os.environ.get("CUDA_VISIBLE_DEVICES")
    os.environ["CUDA_VISIBLE_DEVICES"] = gpu.visible()
    try:
        yield gpu
    finally:
        if previous is None:
            os.environ.pop("CUDA_VISIBLE_DEVICES", None)
        else:
            os.environ["CUDA_VISIBLE_DEVICES"] = previous
        release_flock(fd)


def _holder_words(text: str) -> str:
    try:
        who = json.loads(text)
        return f"pid {who['pid']} on {who['host']} since {who['started']} ({who['job']})"
    except (ValueError, KeyError, TypeError):  # the holder is between its lock and its write
        return "a process that has not named itself yet"


def device_record(device: str) -> dict | None:
    """The header's `device` for a cell run on `device` (runner.device): the CUDA device's nvidia-smi index,
    name and UUID; None on the CPU, so that CPU headers stay as they were."""
    import torch

    dev = torch.device(device)
    if dev.type != "cuda":
        return None
    props = torch.cuda.get_device_properties(dev)
    uuid = str(props.uuid)  # torch prints it as 8-4-4-4-12 hex digits; nvidia-smi and CUDA_VISIBLE_DEVICES add `GPU-`
    uuid = uuid if uuid.startswith("GPU-") else f"GPU-{uuid}"
    index = next((g.index for g in listed_gpus() or [] if g.uuid == uuid), None)
    return {"index": index, "name": props.name, "uuid": uuid}


@dataclass(frozen=True)
class LocalGpuPlan:
    """How a local Snakemake runs a study's GPU jobs: at most `jobs` at once, each in a slot of its own (a device,
    or one of a device's `per_gpu` shares: a small policy leaves a device idle between its simulator steps) and
    `threads` of the node's `cores`, its simulator workers capped at `threads - 1` (one core is the policy
    process's: observations in, CUDA launches out), so that the concurrent jobs' workers fit the node."""

    gpus: tuple[Gpu, ...]
    source: str
    jobs: int
    cores: int
    per_gpu: int = 1

    @classmethod
    def for_node(cls, configured: int | None, requested: int | None, cores: int, per_gpu: int = 1) -> LocalGpuPlan:
        gpus, source = node_gpus(configured)
        return cls(tuple(gpus), source, check_gpu_jobs(requested, gpus, source, per_gpu), cores, per_gpu)

    @property
    def threads(self) -> int:
        return max(1, self.cores // self.jobs)

    def workers(self, num_envs: int) -> int:
        return min(num_envs, max(1, self.threads - 1))

    def describe(self, num_envs: int) -> str:
        devices = ", ".join(f"{g.index}" + (f" {g.name} {g.uuid}" if g.uuid else "") for g in self.gpus)
        where = (f"each in one of a device's {self.per_gpu} slots ({PER_GPU_SETTING})" if self.per_gpu > 1
                 else "each on a device of its own")
        return (f"local GPUs ({self.source}): {devices}; at most {self.jobs} rollout/calibrate jobs at once "
                f"(--resources gpu={self.jobs}), {where} (CUDA_VISIBLE_DEVICES, slots in {SLOTS_DIR}), each with "
                f"{self.threads} of {self.cores} cores and {self.workers(num_envs)} simulator worker(s) "
                f"(study.execution.num_envs: {num_envs})")


@contextmanager
def job_gpu(slots: dict | None, job: str) -> Iterator[Gpu | None]:
    """A Snakemake job's device: a slot of the node's GPUs where the workflow assigns one (rule param
    `gpu_slots`: {dir, gpus, per_gpu}), nothing (None) where it does not (the CPU, SLURM)."""
    if slots is None:
        yield None
        return
    with gpu_slot(slots["dir"], node_gpus(slots["gpus"])[0], job, slots.get("per_gpu", 1)) as gpu:
        print(f"{job}: on GPU {gpu.index} {gpu.name or ''} {gpu.uuid or ''} (CUDA_VISIBLE_DEVICES={gpu.visible()})",
              file=sys.stderr)
        yield gpu
