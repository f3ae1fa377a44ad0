"""Versions and code revision recorded in every cell header (the paper's simulator-version pitfall)."""

from __future__ import annotations

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
