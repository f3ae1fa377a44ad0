"""A real `snakemake tables/lattice.tex --cores 2` on a tiny demo study, in a copy of the workflow:
real LIBERO episodes -> cells -> table; a second run does nothing; changing one cell's preset reruns
only that cell and the tables."""

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from vlaquantbench.records import read_cell
from file_audit import audited_env, job_audits, undeclared
from paths import ROOT

pytestmark = pytest.mark.slow

SNAKEMAKE = [sys.executable, "-m", "snakemake"]
# After the targets (--set-threads takes every word after it). One thread per rollout: the first run's two
# rollouts run at once (a rollout keeps about one core busy: its LIBERO worker and the policy take turns).
# The demo config named: with no --configfile the Snakefile runs the main job (config/main.yaml).
OPTIONS = ["--configfile=config/config.yaml", "--cores", "2", "--set-threads", "rollout=1"]
BASELINE = "libero/libero_spatial/pi05/rtn-BASELINE-e2e"
ATTENTION = "libero/libero_spatial/pi05/ablate-W4A4-ah-onlyself_attn"


def tiny_study(checkout: Path) -> None:
    """The demo config, shrunk: one task, one episode, 10 steps, two cells."""
    config_path = checkout / "config" / "config.yaml"
    config = yaml.safe_load(config_path.read_text())
    config["study"].update(tasks=1, episodes_per_task=1)
    config["study"]["runner"].update(max_steps=10, camera_size=64, flow_steps=2)
    config_path.write_text(yaml.safe_dump(config))
    table_path = checkout / config["study"]["tables_dir"] / "lattice.yaml"
    table = yaml.safe_load(table_path.read_text())
    table["rows"] = [row for row in table["rows"] if row["cell"] == ATTENTION]
    table_path.write_text(yaml.safe_dump(table))


def snakemake(checkout: Path, *args: str, env: dict[str, str] | None = None) -> str:
    result = subprocess.run([*SNAKEMAKE, *args, *OPTIONS], cwd=checkout, capture_output=True, text=True,
                            timeout=1800, env=env)
    assert result.returncode == 0, (result.stdout[-2000:], result.stderr[-4000:])
    return result.stdout + result.stderr


def job_counts(output: str) -> dict[str, int]:
    stats = output.split("Job stats:", 1)[1].split("\n\n", 1)[0] if "Job stats:" in output else ""
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"^(\w+)\s+(\d+)$", stats, re.M) if m.group(1) != "total"}


def workflow_copy(tmp_path: Path) -> Path:
    """A copy of the workflow (Snakefile, rules, scripts, configs) in `tmp_path/checkout`, to run and edit."""
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "config"):
        source = ROOT / item
        (shutil.copytree if source.is_dir() else shutil.copy)(source, checkout / item)
    return checkout


def test_demo_dag_builds_the_table_reruns_nothing_then_only_the_changed_cell(tmp_path):
    checkout = workflow_copy(tmp_path)
    tiny_study(checkout)

    audit = tmp_path / "audit"
    first = snakemake(checkout, "tables/lattice.tex", env=audited_env(audit))
    assert job_counts(first)["rollout"] == 2
    # Each job touched exactly the files its rule declares (the journal as the rollout's `state`).
    assert {job["rule"] for job in job_audits(audit)} == {"download_checkpoint", "rollout", "paper_table"}
    assert undeclared(audit, checkout) == {}
    table = (checkout / "tables" / "lattice.tex").read_text()
    assert "attention" in table and "Demo policy with random weights" in table
    cells = {}
    for header_path in (checkout / "results" / "cells").glob("*/header.json"):
        header = json.loads(header_path.read_text())
        cells[header["ref"]] = header_path.parent
        assert header_path.parent.name == header["config_hash"]
        assert header["chunk"] == {"predicted": 50, "executed": 10}
        assert header["versions"]["mujoco"] == "3.3.2"
        # Random demo weights ran: no revision of the release the study entry names (its config keeps it).
        assert header["revision"] is None and header["config"]["revision"]
        assert header["checkpoint"] == "random weights (demo variant of pi05, seed 0)"
        assert header["hooks"]["fired"] == header["hooks"]["selected"]
    assert set(cells) == {BASELINE, ATTENTION}
    assert read_cell(cells[ATTENTION]).header["hooks"]["selected"] == 72
    assert len(read_cell(cells[ATTENTION]).episodes) == 1
    assert r"\#L" in table and " 72 & " in table

    assert "Nothing to be done" in snakemake(checkout, "-n", "tables/lattice.tex")

    definition = checkout / "config" / "demo" / "tables" / "lattice.yaml"
    definition.write_text(definition.read_text().replace("ablate-W4A4-ah-onlyself_attn", "ablate-W4A8-ah-onlyself_attn"))
    baseline_mtime = (cells[BASELINE] / "episodes.parquet").stat().st_mtime_ns
    second = snakemake(checkout, "tables/lattice.tex")
    counts = job_counts(second)
    assert counts["rollout"] == 1 and counts["paper_table"] == 1
    assert "download_checkpoint" not in counts and "calibrate" not in counts
    assert (cells[BASELINE] / "episodes.parquet").stat().st_mtime_ns == baseline_mtime
    refs = {json.loads(p.read_text())["ref"] for p in (checkout / "results" / "cells").glob("*/header.json")}
    assert refs == {BASELINE, ATTENTION, ATTENTION.replace("W4A4", "W4A8")}
    assert "Nothing to be done" in snakemake(checkout, "-n", "tables/lattice.tex")
