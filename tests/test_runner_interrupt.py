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
    process = subprocess.Popen(
        [sys.executable, "-m", "vlaquantbench.cli", "rollout", REF, "--config", str(config), "--results", str(tmp_path)],
        start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        # A terminal's foreground job has SIGINT at its default. Started in the background (`cmd &`
        # in a script), the suite itself would have it ignored, and the cell would inherit that.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 900

    def journal():
        # `--config` is merged over the checkout's config/config.yaml as Snakemake merges it, so the
        # cell's folder (its config hash) is found rather than recomputed from STUDY alone.
        found = sorted(tmp_path.rglob("journal.jsonl"))
        return found[0] if found else None

    def episodes():
        path = journal()
        lines = path.read_text().splitlines() if path else []
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
    folder = journal().parent
    assert 1 <= done < 3
    message = (f"vqb rollout: interrupted: {REF} has {done} of 3 episodes recorded in {folder}; "
               "run the same command again to resume it")
    # The progress bar may redraw its last state after the message (tqdm closes at exit).
    assert stderr.splitlines().count(message) == 1, stderr[-2000:]
    assert not (folder / "episodes.parquet").exists()
