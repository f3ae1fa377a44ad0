"""The main job: `snakemake --cores 2 tables/lattice.tex` with no --configfile runs config/main.yaml (the pi0.5
trained here, on Meta-World); `--configfile config/config.yaml` runs the random-weight LIBERO demo."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

from paths import ROOT
from vlaquantbench.config import load_workflow_config
from vlaquantbench.workflow import WorkflowConfig


def dry_run(tmp_path: Path, *args: str) -> dict[str, int]:
    """The jobs `snakemake -n tables/lattice.tex <args>` plans in a checkout of the workflow and its committed
    checkpoints: {rule: count}, the cell folders' hashes under "cells"."""
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "config", "src", "checkpoints"):
        (checkout / item).symlink_to(ROOT / item)
    run = subprocess.run([sys.executable, "-m", "snakemake", "-n", "tables/lattice.tex", "--cores", "2", *args],
                         cwd=checkout, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    planned = {job: int(n) for job, n in re.findall(r"^(\w+) +(\d+)$", run.stdout, re.MULTILINE) if job != "total"}
    return {**planned, "cells": set(re.findall(r"results/cells/(\w{12})/header.json", run.stdout))}


def study_cells(config: str) -> dict[str, dict]:
    return WorkflowConfig.from_snakemake(load_workflow_config(ROOT / "config" / config), ROOT).study_cells()


def test_with_no_configfile_the_main_job_runs_the_trained_policy_on_metaworld(tmp_path):
    planned = dry_run(tmp_path)
    cells = study_cells("main.yaml")
    assert planned == {"download_checkpoint": 1, "rollout": 4, "paper_table": 1, "cells": set(cells)}
    training = json.loads((ROOT / "checkpoints" / "pi05_metaworld" / "training.json").read_text())
    assert sorted(f"{c['method']}-{c['preset']}-{c['scope']}" for c in cells.values()) == [
        "rtn-BASELINE-e2e", "rtn-W2A2-e2e", "rtn-W4A4-ah", "rtn-W8A8-e2e"]
    for cell in cells.values():
        assert (cell["benchmark"], cell["suite"], cell["variant"]) == ("metaworld", "metaworld_mt50", "full")
        assert (cell["checkpoint"], cell["revision"]) == (training["checkpoint"], training["revision"])
        # What the training fixed: the input size and the executed part of each chunk.
        assert cell["runner"]["camera_size"] == 112 and cell["runner"]["executed_chunk"] == 5


def test_the_demo_config_still_runs_the_random_weight_libero_demo(tmp_path):
    planned = dry_run(tmp_path, "--configfile=config/config.yaml")
    cells = study_cells("config.yaml")
    assert planned["rollout"] == 5 and planned["cells"] == set(cells)
    assert {(c["benchmark"], c["variant"]) for c in cells.values()} == {("libero", "demo")}
