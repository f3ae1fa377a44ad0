"""The cell journal: durable appends, torn last lines, refused header mismatches, episodes recorded twice\n(alike: resumed once; differently: refused naming the lines)."""

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from vlaquantbench.errors import UserError
from vlaquantbench.runner.journal import CellJournal, recorded_episodes, recorded_keys

HEADER = {"config_hash": "0123456789ab", "model": "pi05", "benchmark": "libero", "suite": "libero_spatial", "seed": 0,
          "episodes_per_task": 20, "preset": "W4A4", "versions": {"mujoco": "3.3.2"}}


def episode(task_id, n, success=False):
    return {"suite": "libero_spatial", "task_id": task_id, "episode": n, "seed": 1009 * task_id + n,
            "init_state_id": n, "success": success, "steps": 30}


def test_appends_survive_reopening_and_resume_where_they_stopped(tmp_path):
    path = tmp_path / "cell" / "journal.jsonl"
    journal = CellJournal(path, HEADER)
    journal.record([episode(0, 0), episode(0, 1, success=True)], fired={"a", "b"})
    journal.record([episode(1, 0)], fired={"a", "b"})
    reopened = CellJournal(path, HEADER)
    assert reopened.episodes == [episode(0, 0), episode(0, 1, success=True), episode(1, 0)]
    assert reopened.done_keys() == {(0, 0, 0), (0, 1, 1), (1, 0, 1009)}
    assert reopened.fired == {"a", "b"}
    kinds = [json.loads(line)["kind"] for line in path.read_text().splitlines()]
    assert kinds == ["header", "hooks", "episode", "episode", "episode"]  # hooks only written when they grow


def test_a_torn_last_line_is_dropped_and_later_appends_stay_readable(tmp_path):
    path = tmp_path / "journal.jsonl"
    CellJournal(path, HEADER).record([episode(0, 0)], fired=set())
    with open(path, "a") as handle:  # what a kill -9 in the middle of a write leaves
        handle.write('{"kind": "episode", "suite": "libero_spa')
    journal = CellJournal(path, HEADER)
    assert journal.done_keys() == {(0, 0, 0)}
    journal.record([episode(0, 1)], fired=set())
    assert CellJournal(path, HEADER).done_keys() == {(0, 0, 0), (0, 1, 1)}


def test_a_different_header_is_refused_with_both_values_and_nothing_is_lost(tmp_path):
    path = tmp_path / "journal.jsonl"
    CellJournal(path, HEADER).record([episode(0, 0)], fired=set())
    before = path.read_bytes()
    other = {**HEADER, "preset": "W4A8", "versions": {"mujoco": "3.4.0"}}
    with pytest.raises(UserError) as err:
        CellJournal(path, other)
    message = str(err.value)
    assert str(path) in message
    assert 'preset: recorded="W4A4" current="W4A8"' in message
    assert 'versions: recorded={"mujoco": "3.3.2"} current={"mujoco": "3.4.0"}' in message
    assert path.read_bytes() == before


def test_an_episode_recorded_twice_alike_resumes_once(tmp_path):
    """Two writers of one cell (before the writer lock) recorded each episode twice: same outcome and
    digest, other timing. The journal resumes with each episode once."""
    path = tmp_path / "journal.jsonl"
    journal = CellJournal(path, HEADER)
    journal.record([{**episode(0, 0), "wall_time_s": 1.5}, episode(0, 1, success=True)], fired={"a"})
    journal.record([{**episode(0, 0), "wall_time_s": 2.5}], fired={"a", "b"})
    reopened = CellJournal(path, HEADER)
    assert reopened.episodes == [{**episode(0, 0), "wall_time_s": 1.5}, episode(0, 1, success=True)]
    assert reopened.fired == {"a", "b"}
    assert recorded_episodes(path) == 2 and recorded_keys(path) == {(0, 0, 0), (0, 1, 1)}


def test_an_episode_recorded_twice_differently_is_refused_naming_file_lines_and_remedy(tmp_path):
    path = tmp_path / "cell" / "journal.jsonl"
    journal = CellJournal(path, HEADER)
    journal.record([episode(0, 0), episode(0, 1)], fired=set())  # lines 2, 3
    journal.record([episode(0, 1, success=True)], fired=set())  # line 4
    before = path.read_bytes()
    for read in (lambda: CellJournal(path, HEADER), lambda: recorded_keys(path)):
        with pytest.raises(UserError) as err:
            read()
        message = str(err.value)
        assert message.startswith(f"{path}: episodes recorded twice with different outcomes")
        assert "lines 3 and 4: {'task_id': 0, 'episode': 1, 'seed': 1} (success: false vs true)" in message
        assert f"Delete both lines of each pair from {path}" in message and f"move {path.parent} away" in message
    assert path.read_bytes() == before
    # The remedy works: without both lines the episode is missing again and runs on resume.
    lines = before.decode().splitlines(keepends=True)
    path.write_text("".join(lines[:2] + lines[4:]))
    assert CellJournal(path, HEADER).done_keys() == {(0, 0, 0)}


def test_vqb_rollout_refuses_a_journal_with_conflicting_duplicates_before_anything_runs(tmp_path):
    ref = "libero/libero_spatial/pi05/rtn-W4A4-ah"
    config = tmp_path / "study.yaml"
    config.write_text(yaml.safe_dump({"study": {"models": {"pi05": {"variant": "demo"}}, "tasks": [0],
                                                "episodes_per_task": 2}}))
    command = [sys.executable, "-m", "vlaquantbench.cli", "rollout", ref, "--config", str(config), "--results", str(tmp_path)]
    folder = Path(json.loads(subprocess.run([*command, "--show"], capture_output=True, text=True, check=True,
                                            timeout=300).stdout)["folder"])
    path = folder / "journal.jsonl"
    journal = CellJournal(path, HEADER)
    journal.record([episode(0, 0), episode(0, 1)], fired=set())
    journal.record([episode(0, 0, success=True)], fired=set())
    before = path.read_bytes()
    began = time.monotonic()
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert result.returncode == 2
    assert result.stderr.startswith(f"vqb rollout: error: {path}: episodes recorded twice with different outcomes")
    assert "lines 2 and 4: {'task_id': 0, 'episode': 0, 'seed': 0} (success: false vs true)" in result.stderr
    assert "Traceback" not in result.stderr
    assert time.monotonic() - began < 60  # no policy loaded, no LIBERO worker started
    assert path.read_bytes() == before and not (folder / "episodes.parquet").exists()
