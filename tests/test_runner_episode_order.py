"""`study.execution.episode_order: interleaved` (issue 32): a cell runs round-robin over its tasks, resumes a
journal begun in the other order, and ends with the same episodes as a task-by-task run of one env."""

import json

import pandas as pd
import pytest
from demo_study import demo_study

from vlaquantbench.cells import cell_config
from vlaquantbench.config.study import StudyConfig
from vlaquantbench.errors import UserError
from vlaquantbench.runner.cell import CellRun, episode_keys, run_cell

REF = "libero/libero_spatial/pi05/rtn-W4A4-ah"
STUDY = {**demo_study(episodes_per_task=2), "tasks": [0, 1]}


def test_episode_keys_interleave_rounds_and_refuse_an_unknown_order():
    assert episode_keys([0, 1, 2], 2, "task_major") == [(0, 0), (0, 1), (1, 0), (1, 1), (2, 0), (2, 1)]
    assert episode_keys([0, 1, 2], 2, "interleaved") == [(0, 0), (1, 0), (2, 0), (0, 1), (1, 1), (2, 1)]
    with pytest.raises(UserError, match="episode_order: 'random' is not one of task_major, interleaved"):
        episode_keys([0], 1, "random")
    with pytest.raises(UserError, match="episode_order"):
        StudyConfig.from_dict({"execution": {"episode_order": "round_robin"}})
    assert StudyConfig.from_dict({"execution": {"episode_order": "interleaved"}}).execution.episode_order == "interleaved"


def _journal(folder):
    return [json.loads(line) for line in (folder / "journal.jsonl").read_text().splitlines()]


def _key(record):
    return record["task_id"], record["episode"]


@pytest.mark.slow
def test_interleaved_run_resumes_a_task_major_journal_and_records_the_same_episodes(tmp_path):
    cfg = cell_config(REF, STUDY)
    task_major = tmp_path / "task_major"
    run_cell(cfg, task_major, progress=False, num_envs=1)
    reference = pd.read_parquet(task_major / "episodes.parquet")
    assert list(zip(reference["task_id"], reference["episode"])) == [(0, 0), (0, 1), (1, 0), (1, 1)]

    # Interrupted after its first episode (task 0, episode 0), then rerun interleaved with two envs.
    interleaved = tmp_path / "interleaved"
    interleaved.mkdir()
    lines = (task_major / "journal.jsonl").read_text().splitlines(keepends=True)
    first_episode = next(n for n, line in enumerate(lines) if json.loads(line)["kind"] == "episode")
    (interleaved / "journal.jsonl").write_text("".join(lines[: first_episode + 1]))
    run = CellRun(cfg, interleaved, progress=False, num_envs=2, episode_order="interleaved")
    assert [(s.task_id, s.episode) for s in run.specs] == [(0, 0), (1, 0), (0, 1), (1, 1)]
    run.start_env()
    run.prepare()
    run.run()

    episodes = [record for record in _journal(interleaved) if record["kind"] == "episode"]
    # Only the three missing episodes ran, in rounds: round 0's task 1 with round 1's task 0, then the rest.
    assert _key(episodes[0]) == (0, 0) and len(episodes) == 4
    assert {_key(r) for r in episodes[1:3]} == {(1, 0), (0, 1)} and _key(episodes[3]) == (1, 1)
    resumed = pd.read_parquet(interleaved / "episodes.parquet")
    assert list(zip(resumed["task_id"], resumed["episode"])) == [(0, 0), (1, 0), (0, 1), (1, 1)]  # the run's order
    columns = ["task_id", "episode", "seed", "init_state_id", "success", "steps"]
    by_key = ["task_id", "episode"]
    pd.testing.assert_frame_equal(resumed[columns].sort_values(by_key).reset_index(drop=True),
                                  reference[columns].sort_values(by_key).reset_index(drop=True))
    digests = {_key(r): r["actions_sha256"] for r in _journal(task_major) if r["kind"] == "episode"}
    assert {_key(r): r["actions_sha256"] for r in episodes} == digests  # every executed action the same
    assert len(set(digests.values())) == 4  # the episodes really differ
