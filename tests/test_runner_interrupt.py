"""Ctrl-C during a real `vqb rollout`: one line saying how far the cell got and that rerunning resumes
it, no traceback, exit 130, the journal intact."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import yaml

from vlaquantbench.cells import cell_config, config_hash
from vlaquantbench.workflow import CELLS_DIR

pytestmark = pytest.mark.slow

REF = "libero/libero_spatial/pi05/rtn-W4A4-ah"
STUDY = {
    "models": {"pi05": {"variant": "demo", "checkpoint": "lerobot/pi05_libero_finetuned_v044"}},
    "tasks": [0],
    "episodes_per_task": 3,
    "runner": {"max_steps": 10, "camera_size": 64, "flow_steps": 2},
    "execution": {"num_envs": 1},
}


def test_ctrl_c_prints_how_far_the_cell_got_and_that_rerunning_resumes(tmp_path):
    config = tmp_path / "study.yaml"
    config.write_text(yaml.safe_dump({"study": STUDY}))
    folder = tmp_path / CELLS_DIR / config_hash(cell_config(REF, STUDY))
    journal = folder / "journal.jsonl"
    process = subprocess.Popen(
        [sys.executable, "-m", "vlaquantbench.cli", "rollout", REF, "--config", str(config), "--results", str(tmp_path)],
        start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    deadline = time.monotonic() + 900

    def episodes():
        lines = journal.read_text().splitlines() if journal.exists() else []
        return sum(json.loads(line)["kind"] == "episode" for line in lines)

    while episodes() < 1:
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "no episode finished in time"
        time.sleep(0.2)
    os.killpg(process.pid, signal.SIGINT)  # what a terminal's Ctrl-C does: the whole foreground group
    _, stderr = process.communicate(timeout=120)

    assert process.returncode == 130
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr
    done = episodes()
    assert 1 <= done < 3
    last = stderr.strip().splitlines()[-1]
    assert last == (f"vqb rollout: interrupted: {REF} has {done} of 3 episodes recorded in {folder}; "
                    "run the same command again to resume it")
    assert not (folder / "episodes.parquet").exists()
