"""Cells on real LIBERO episodes: kill -9 mid-cell then rerun; a hook that never fires; a header mismatch."""

import json
import os
import signal
import subprocess
import sys
import time

import pandas as pd
import pytest

from vlaquantbench.cells import cell_config
from vlaquantbench.errors import UserError
from vlaquantbench.runner.cell import CellFailed, CellRun, run_cell

pytestmark = pytest.mark.slow

STUDY = {
    "models": {"pi05": {"variant": "demo", "checkpoint": "lerobot/pi05_libero_finetuned_v044"}},
    "tasks": [0],
    "episodes_per_task": 3,
    "runner": {"max_steps": 10, "camera_size": 64, "flow_steps": 2},
}
REF = "libero/libero_spatial/pi05/ablate-W4A4-ah-onlyself_attn"
RUN_CELL = "import json, sys; from vlaquantbench.runner.cell import run_cell; run_cell(json.loads(sys.argv[1]), sys.argv[2], num_envs=1)"


def journal_lines(path):
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def outcomes(folder):
    """(task, episode, seed) -> (success, steps, digest of every executed action) from the journal."""
    return {
        (r["task_id"], r["episode"], r["seed"]): (r["success"], r["steps"], r["actions_sha256"])
        for r in journal_lines(folder / "journal.jsonl")
        if r["kind"] == "episode"
    }


def test_kill_9_mid_cell_then_rerun_gives_exactly_the_uninterrupted_episodes(tmp_path):
    cfg = cell_config(REF, STUDY)
    interrupted = tmp_path / "interrupted"
    process = subprocess.Popen(
        [sys.executable, "-c", RUN_CELL, json.dumps(cfg), str(interrupted)], start_new_session=True
    )
    journal = interrupted / "journal.jsonl"
    deadline = time.monotonic() + 900
    while not any(r["kind"] == "episode" for r in journal_lines(journal)):
        assert process.poll() is None, "the cell ended before it could be killed"
        assert time.monotonic() < deadline, "no episode finished in time"
        time.sleep(0.2)
    os.killpg(process.pid, signal.SIGKILL)  # the runner and its LIBERO workers, mid-cell
    process.wait()
    done_before = outcomes(interrupted)
    assert 1 <= len(done_before) < 3
    assert not (interrupted / "episodes.parquet").exists()  # the workflow sees no output yet

    run_cell(cfg, interrupted, num_envs=1, progress=False)
    uninterrupted = tmp_path / "uninterrupted"
    run_cell(cfg, uninterrupted, num_envs=2, progress=False)

    resumed = outcomes(interrupted)
    assert len([r for r in journal_lines(journal) if r["kind"] == "episode"]) == 3  # nothing ran twice
    assert resumed == outcomes(uninterrupted)
    assert {k: resumed[k] for k in done_before} == done_before
    episodes = pd.read_parquet(interrupted / "episodes.parquet")
    assert list(zip(episodes.task_id, episodes.episode, episodes.seed)) == [(0, 0, 0), (0, 1, 1), (0, 2, 2)]
    timing = ["wall_time_s", "policy_latency_mean_s"]
    other = pd.read_parquet(uninterrupted / "episodes.parquet")
    assert episodes.drop(columns=timing).equals(other.drop(columns=timing))


def test_a_selected_layer_whose_hook_never_runs_fails_the_cell(tmp_path):
    cfg = cell_config(REF, {**STUDY, "episodes_per_task": 1})
    run = CellRun(cfg, tmp_path, progress=False)
    run.prepare()
    skipped = "paligemma_with_expert.gemma_expert.model.layers.3.self_attn.v_proj"
    run.report.result.hooks[skipped].remove()  # as if the adapter bypassed this layer's input hook
    with pytest.raises(CellFailed, match=rf"1 of 72 selected layers' activation hooks never fired.*{skipped}"):
        run.run()
    assert not (tmp_path / "episodes.parquet").exists() and not (tmp_path / "header.json").exists()
    assert len(outcomes(tmp_path)) == 1  # the episode itself is kept in the journal


def test_a_rerun_with_another_header_is_refused_showing_both_values(tmp_path):
    cfg = cell_config(REF, {**STUDY, "episodes_per_task": 1})
    journal = tmp_path / "journal.jsonl"
    journal.write_text(json.dumps({"kind": "header", "config_hash": "000000000000", "preset": "W4A8"}) + "\n")
    before = journal.read_bytes()
    with pytest.raises(UserError) as err:
        run_cell(cfg, tmp_path, progress=False)
    message = str(err.value)
    assert 'preset: recorded="W4A8" current="W4A4"' in message
    assert 'config_hash: recorded="000000000000"' in message
    assert journal.read_bytes() == before
