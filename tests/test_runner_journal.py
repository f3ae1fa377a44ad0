"""The cell journal: durable appends, torn last lines, refused header mismatches, no duplicates."""

import json

import pytest

from vlaquantbench.errors import UserError
from vlaquantbench.runner.journal import CellJournal

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


def test_duplicate_episode_keys_in_a_journal_are_an_error_naming_it(tmp_path):
    path = tmp_path / "journal.jsonl"
    journal = CellJournal(path, HEADER)
    journal.record([episode(0, 0)], fired=set())
    journal.record([episode(0, 0)], fired=set())
    with pytest.raises(UserError, match=rf"{path}: duplicate episode"):
        CellJournal(path, HEADER)
