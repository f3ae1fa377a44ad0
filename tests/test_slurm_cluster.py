"""The demo study on a real single-node SLURM cluster (`scripts/local_slurm.sh`), through
`--profile profiles/slurm` with CPU-only overrides: one SLURM job per cell, a calibration job and the
analysis jobs; while it runs, one rollout job is requeued (`scontrol requeue`), one is cancelled
(`scancel`) and one hits its time limit. Snakemake's retry resubmits the failed ones, each rollout
resumes from its journal, and the cells' episodes and the final table equal an uninterrupted local run's
byte for byte. The local run starts first and runs beside the cluster's install and run: the cluster
run waits on sbatch, status checks and slurmctld's time-limit check most of the time, and the local
run's jobs use those idle cores. Select with `pytest -k slurm`; skipped (with the reason printed) only
where apt cannot install slurm-wlm and munge, or where the test does not run as root."""

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from paths import ROOT

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(os.geteuid() != 0, reason="the SLURM test installs and starts a cluster as root; not root here"),
]

CLUSTER = ROOT / "scripts" / "local_slurm.sh"
SNAKEMAKE = [sys.executable, "-m", "snakemake"]
# Enough episodes that a job whose time limit is cut after a cell's first episode is still running when
# slurmctld next enforces limits: it checks every 30 s (PERIODIC_TIMEOUT in slurmctld, not configurable)
# and an episode here takes about 10 s (2 cores, beside the local run), so 4-5 are left at the cut.
EPISODES = 6
TABLE_CELLS = [
    "libero/libero_spatial/pi05/ablate-W4A4-ah-onlyself_attn",
    "libero/libero_spatial/pi05/calib_ah-W4A4-ah-onlyself_attn",
]
# The profile's cluster resources (GPU partition, 8 CPUs, 64 GB) replaced by what one 2-core node has.
CPU_ONLY = [
    "--default-resources", "slurm_partition=cpu", "cpus_per_task=1", "mem_mb=3000", "runtime=20",
    "--set-resources", "rollout:slurm_partition=cpu", "rollout:cpus_per_task=1", "rollout:mem_mb=3000",
    "rollout:runtime=20", "calibrate:slurm_partition=cpu", "calibrate:cpus_per_task=1",
    "calibrate:mem_mb=3000", "calibrate:runtime=20",
    "--set-threads", "rollout=1", "calibrate=1",
    # No accounting on this cluster: sacct answers nothing and the executor would lose its jobs.
    "--slurm-status-command", "squeue",
    "--slurm-init-seconds-before-status-checks", "1",
    "--jobs", "3",
]


@pytest.fixture(scope="module")
def local_run(tmp_path_factory):
    """The uninterrupted reference: the demo study run locally, started before the cluster is installed
    and left running beside the cluster run (the test waits for it after). Two jobs at a time."""
    checkout = demo_checkout(tmp_path_factory.mktemp("slurm_local") / "local")
    with (checkout.parent / "snakemake.log").open("w") as log:
        process = subprocess.Popen(
            [*SNAKEMAKE, "tables/lattice.tex", "--configfile=config/config.yaml", "--cores", "2", "--set-threads",
             "rollout=1", "calibrate=1"],
            cwd=checkout, stdout=log, stderr=subprocess.STDOUT, text=True, start_new_session=True,
        )
    yield checkout, process
    if process.poll() is None:  # the test failed before waiting for it: stop its jobs and their LIBERO workers too
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()


@pytest.fixture(scope="module")
def slurm_cluster():
    installed = subprocess.run(["bash", str(CLUSTER), "install"], capture_output=True, text=True, timeout=1500)
    if installed.returncode != 0:
        reason = f"apt cannot install slurm-wlm/munge: {(installed.stdout + installed.stderr)[-500:]}"
        print(reason)
        pytest.skip(reason)
    started = subprocess.run(["bash", str(CLUSTER), "start"], capture_output=True, text=True, timeout=120)
    assert started.returncode == 0, started.stdout + started.stderr
    yield
    subprocess.run(["bash", str(CLUSTER), "stop"], capture_output=True, text=True, timeout=120)


def demo_checkout(path: Path) -> Path:
    """The demo workflow shrunk to one task, EPISODES 10-step episodes, three cells (one calibrated)."""
    path.mkdir()
    for item in ("Snakefile", "rules", "workflow", "config", "profiles"):
        source = ROOT / item
        (shutil.copytree if source.is_dir() else shutil.copy)(source, path / item)
    config_path = path / "config" / "config.yaml"
    config = yaml.safe_load(config_path.read_text())
    study = config["study"]
    study.update(tasks=1, episodes_per_task=EPISODES)
    study["runner"].update(max_steps=10, camera_size=64, flow_steps=2)
    study["calibration"] = {"episodes": 1, "tasks": 1}
    study["execution"]["num_envs"] = 1
    config_path.write_text(yaml.safe_dump(config))
    table_path = path / study["tables_dir"] / "lattice.yaml"
    table = yaml.safe_load(table_path.read_text())
    table["rows"] = [{"label": ref.rsplit("/", 1)[1], "cell": ref} for ref in TABLE_CELLS]
    table_path.write_text(yaml.safe_dump(table))
    return path


def cell_episodes(checkout: Path) -> dict[str, list[dict]]:
    """Cell reference -> its episode lines from the journal, in journal order (duplicates kept)."""
    cells = {}
    for journal in (checkout / "results" / "cells").glob("*/journal.jsonl"):
        lines = [json.loads(line) for line in journal.read_text().splitlines()]
        cells[lines[0]["ref"]] = [line for line in lines if line["kind"] == "episode"]
    return cells


def comparable(episode: dict) -> dict:
    """An episode line without what legitimately differs between two runs (wall-clock timings)."""
    return {k: v for k, v in episode.items() if "latency" not in k and "time" not in k}


def squeue() -> list[tuple[str, str, str]]:
    """(job id, state, comment) of this cluster's jobs; the executor puts the rule name in the comment."""
    out = subprocess.run(["squeue", "-h", "-o", "%i|%T|%k"], capture_output=True, text=True).stdout
    return [tuple(line.split("|", 2)) for line in out.splitlines() if line.count("|") == 2]


class FaultInjector(threading.Thread):
    """Interrupts the first three rollout jobs once each, each after a cell has recorded an episode:
    time limit cut to zero (its end time is now: slurmctld kills it with TIMEOUT at its next check,
    within 30 s; Snakemake retries it with the profile's runtime), scancel (a failed job: Snakemake
    retries it), requeue (the same job id runs again). The time limit goes first: it takes effect last.
    (`TimeLimit=0:01` would be one minute after the job's start: slurm rounds limits up to minutes.)"""

    FAULTS = ("timeout", "scancel", "requeue")

    def __init__(self, checkout: Path, deadline_s: float):
        super().__init__(daemon=True)
        self.checkout, self.deadline = checkout, time.monotonic() + deadline_s
        self.done: dict[str, str] = {}  # fault -> SLURM job id
        self.stop = threading.Event()

    def journal_lengths(self) -> dict[str, int]:
        return {ref: len(eps) for ref, eps in cell_episodes(self.checkout).items()}

    def run(self) -> None:
        hit: set[str] = set()
        while not self.stop.is_set() and time.monotonic() < self.deadline and len(self.done) < len(self.FAULTS):
            running = [job for job, state, comment in squeue() if state == "RUNNING" and "rule_rollout" in comment]
            recorded = self.journal_lengths()
            if running and any(n >= 1 for n in recorded.values()):
                for job in running:
                    if job in hit:
                        continue
                    fault = self.FAULTS[len(self.done)]
                    if fault == "requeue":
                        command = ["scontrol", "requeue", job]
                    elif fault == "scancel":
                        command = ["scancel", job]
                    else:
                        command = ["scontrol", "update", f"JobId={job}", "TimeLimit=0"]
                    if subprocess.run(command, capture_output=True).returncode == 0:
                        hit.add(job)
                        self.done[fault] = job
                    break
            time.sleep(0.5)


def test_slurm_demo_study_survives_requeue_scancel_and_time_limit(local_run, slurm_cluster, tmp_path):
    cluster = demo_checkout(tmp_path / "cluster")
    injector = FaultInjector(cluster, deadline_s=1200)
    injector.start()
    result = subprocess.run(
        [*SNAKEMAKE, "tables/lattice.tex", "--configfile=config/config.yaml", "--profile", "profiles/slurm", *CPU_ONLY],
        cwd=cluster, capture_output=True, text=True, timeout=1500,
    )
    injector.stop.set()
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-4000:]
    local, local_process = local_run
    assert local_process.wait(timeout=1500) == 0, (local.parent / "snakemake.log").read_text()[-3000:]

    # One SLURM job per cell (3 rollouts), the calibration and download jobs and the table job (which checks
    # its own records: no manifest job runs for it), each submitted through sbatch; the cancelled and
    # timed-out rollouts once more.
    submitted = output.count("has been submitted with SLURM jobid")
    assert "rule_rollout" in output and "rule_calibrate" in output and "rule_paper_table" in output
    assert set(injector.done) == {"requeue", "scancel", "timeout"}, injector.done
    assert "TIMEOUT" in output and "CANCELLED" in output, output[-4000:]
    assert submitted >= 3 + 2 + 1 + 2, output[-4000:]

    # Every cell's journal holds each episode exactly once, equal to the uninterrupted local run's.
    local_cells, cluster_cells = cell_episodes(local), cell_episodes(cluster)
    assert set(cluster_cells) == set(local_cells) and len(local_cells) == 3
    for ref, episodes in cluster_cells.items():
        keys = [(e["task_id"], e["episode"], e["seed"]) for e in episodes]
        assert len(keys) == len(set(keys)) == EPISODES, (ref, keys)
        by_key = {(e["task_id"], e["episode"], e["seed"]): comparable(e) for e in episodes}
        reference = {(e["task_id"], e["episode"], e["seed"]): comparable(e) for e in local_cells[ref]}
        assert by_key == reference, ref

    assert (cluster / "tables" / "lattice.tex").read_bytes() == (local / "tables" / "lattice.tex").read_bytes()
    # Each rule's own log lies under logs/, beside SLURM's under .snakemake/slurm_logs/.
    assert list((cluster / ".snakemake" / "slurm_logs").glob("rule_rollout/*/*.log"))
    assert len(list((cluster / "logs" / "rollout").glob("*.log"))) == 3
    assert list((cluster / "logs" / "calibrate").glob("*.log"))
