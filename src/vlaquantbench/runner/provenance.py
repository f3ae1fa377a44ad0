"""Versions and code revision recorded in every cell header (the paper's simulator-version pitfall)."""

from __future__ import annotations

import os
import platform
import subprocess
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path


def _version(package: str) -> str | None:
    try:
        return version(package)
    except PackageNotFoundError:
        return None


def versions() -> dict[str, str | None]:
    return {
        "mujoco": _version("mujoco"),
        "torch": _version("torch"),
        "lerobot": _version("lerobot"),
        "python": platform.python_version(),
        "vlaquantbench": _version("vlaquantbench"),
    }


def host() -> dict:
    """What the episodes also depend on beyond the versions: the CPU (its model, and the instruction set
    torch's CPU kernels dispatch to: float32 sums are rounded differently across them), MuJoCo's rendering
    backend, which the simulator workers inherit (`egl` when unset), and the GPUs nvidia-smi lists, one of
    which an EGL context renders on where there are any (otherwise Mesa renders on the CPU). A closed loop
    amplifies any last-bit difference: the methods study's cells, recorded on an H200 host's Xeon with EGL on
    its GPU and re-run on an AMD EPYC without a GPU, kept 27-29 of 30 outcomes and 14-18 of 30 step counts
    (benchmarks/rerun_agreement.py)."""
    import torch

    from vlaquantbench.runner.gpus import listed_gpus

    return {"cpu": _cpu_model(), "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "mujoco_gl": os.environ.get("MUJOCO_GL", "egl"), "gpus": sorted(g.name for g in listed_gpus() or [])}


def _cpu_model() -> str:
    """The first `model name` of /proc/cpuinfo (Linux), else what the platform module says."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        lines = []
    return next((line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")), platform.processor())


def code_revision(source: Path | None = None) -> str:
    """`<short commit>[-dirty]` of the checkout holding this package, or `unknown` outside git."""
    root = source or Path(__file__).resolve().parents[3]
    try:
        commit = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
        status = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no", "--", "src"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return f"{commit}-dirty" if status else commit
