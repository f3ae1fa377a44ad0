"""`snakemake --profile profiles/slurm -n`: the paper study plans GPU rollout jobs and CPU-only analysis jobs."""

import re
import shutil
import subprocess
import sys
from pathlib import Path
from paths import ROOT

from vlaquantbench.envs.memory import job_memory_mb

SNAKEMAKE = [sys.executable, "-m", "snakemake"]


def workflow_copy(tmp_path: Path) -> Path:
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "config", "profiles"):
        source = ROOT / item
        (shutil.copytree if source.is_dir() else shutil.copy)(source, checkout / item)
    return checkout


def jobs_by_rule(output: str) -> dict[str, list[str]]:
    """Rule name -> the `resources:` line of each planned job."""
    jobs: dict[str, list[str]] = {}
    for block in re.split(r"\n(?=(?:localrule|rule) \w+:)", output):
        match = re.match(r"(?:localrule|rule) (\w+):", block)
        if match:
            resources = re.search(r"resources: (.*)", block)
            jobs.setdefault(match.group(1), []).append(resources.group(1) if resources else "")
    return jobs


def test_slurm_profile_dry_run_puts_rollouts_on_gpus(tmp_path):
    checkout = workflow_copy(tmp_path)
    result = subprocess.run(
        [*SNAKEMAKE, "--profile", "profiles/slurm", "--configfile", "config/paper.yaml", "-n"],
        cwd=checkout,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    output = result.stdout + result.stderr
    assert "Using profile profiles/slurm" in output
    jobs = jobs_by_rule(output)
    # tab:lattice (14 subsets + baseline) and tab:calibrated_subsets share cells: one job per distinct cell.
    assert len(jobs["rollout"]) == 22
    assert len(jobs["calibrate"]) == 1 and len(jobs["download_checkpoint"]) == 1
    for resources in jobs["rollout"] + jobs["calibrate"]:
        assert "slurm_partition=gpu" in resources and "gpu=1" in resources
    # Memory follows from the worker count (config/paper.yaml: num_envs 8; a calibration has 2 episodes), not a
    # fixed 64 GB: each LIBERO worker's measured footprint plus the policy's.
    for rule, workers in (("rollout", 8), ("calibrate", 2)):
        for resources in jobs[rule]:
            assert f"mem_mb={job_memory_mb('libero', 'libero_spatial', workers)}," in resources, (rule, resources)
    for rule in ("download_checkpoint", "paper_table", "summary", "records_manifest"):
        for resources in jobs[rule]:
            assert "slurm_partition=cpu" in resources and "gpu=" not in resources, (rule, resources)
    assert not (checkout / "results" / "cells").exists()  # a dry run submits and writes nothing
