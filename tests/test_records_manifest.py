"""Manifests: the committed reference manifest, portability, and verification errors naming the file."""

import json
import shutil
from dataclasses import replace
from pathlib import Path

import pytest

from vlaquantbench.cli import main
from vlaquantbench.errors import UserError
from vlaquantbench.manifest import read_manifest, verify_manifest, write_manifest
from vlaquantbench.records import episode_gaps, read_cell
from paths import ROOT, RECORDS

FROZEN = ROOT / "manifests" / "reference.tsv"
CELL = Path("libero/libero_spatial/pi05/ablate-W4A4-ah-onlyadarms.jsonl")


@pytest.fixture
def records_copy(tmp_path):
    copy = tmp_path / "records"
    shutil.copytree(RECORDS, copy)
    for path in copy.rglob("*"):
        path.chmod(0o755 if path.is_dir() else 0o644)
    return copy


def test_committed_manifest_is_the_reference_records(tmp_path):
    rows = read_manifest(FROZEN)
    assert len(rows) == 65 and rows[CELL.as_posix()].successes == 187
    assert write_manifest(RECORDS, tmp_path / "m.tsv").read_text() == FROZEN.read_text()
    assert len(verify_manifest(FROZEN, RECORDS)) == 65


def test_manifest_is_portable(records_copy, tmp_path):
    assert write_manifest(records_copy, tmp_path / "m.tsv").read_text() == FROZEN.read_text()


def test_changed_record_is_named(records_copy):
    path = records_copy / CELL
    lines = path.read_text().splitlines()
    flipped = next(i for i, line in enumerate(lines) if '"success": false' in line)
    lines[flipped] = lines[flipped].replace('"success": false', '"success": true')
    path.write_text("\n".join(lines) + "\n")
    episode = json.loads(lines[flipped])
    with pytest.raises(UserError, match=rf"record {path} does not match manifest") as refused:
        verify_manifest(FROZEN, records_copy)
    # what changed, not only that the hash differs: the count and the line of the flipped outcome
    assert "188 successes instead of 187" in str(refused.value)
    assert (f"line {flipped + 1} (task {episode['task_id']}, episode {episode['episode']}): success false -> true"
            in str(refused.value))  # fmt: skip


def test_missing_episode_line_is_explained_with_the_manifest(records_copy):
    path = records_copy / CELL
    lines = path.read_text().splitlines()
    removed = json.loads(lines.pop(57))  # task 2, episode 16
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(UserError, match="199 episodes instead of 200") as refused:
        verify_manifest(FROZEN, records_copy)
    assert f"task {removed['task_id']} lacks episode(s) {removed['episode']}" in str(refused.value)


def test_missing_episode_line_is_refused_without_a_manifest(records_copy, tmp_path):
    """With `manifest=` empty the manifest is built from the records: a hole in a cell stops it, by name."""
    path = records_copy / CELL
    lines = path.read_text().splitlines()
    removed = json.loads(lines.pop(57))  # task 2, episode 16
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(UserError, match=rf"{path}: episodes do not match the header: task {removed['task_id']} lacks"):
        write_manifest(records_copy, tmp_path / "m.tsv")


def test_header_declared_counts_are_followed():
    """The authors' X-VLA cells hold 19 episodes per task under `episodes_per_task: 20`: legitimate, no hole."""
    xvla = read_cell(RECORDS / "libero/libero_spatial/xvla/rtn-BASELINE-e2e.jsonl")
    assert xvla.n_episodes == 190 and xvla.header["episodes_per_task"] == 20 and episode_gaps(xvla) == []
    cell = read_cell(RECORDS / CELL)
    complete = replace(cell, header={**cell.header, "tasks": list(range(11))})  # a project header lists its tasks
    assert episode_gaps(complete) == ["task 10 (listed in the header) has no episodes"]
    project = replace(cell, header={**cell.header, "config": {"tasks": list(range(10))}},
                      episodes=cell.episodes[~((cell.episodes["task_id"] == 9) & (cell.episodes["episode"] == 19))])
    assert episode_gaps(project) == ["task 9 lacks episode(s) 19"]  # a listed task's last episode is required too
    over = replace(cell, header={**cell.header, "episodes_per_task": 19})
    assert "task 0 has 20 episodes, the header declares 19 per task" in episode_gaps(over)


def test_missing_and_unlisted_records_are_named(records_copy, tmp_path):
    (records_copy / CELL).unlink()
    with pytest.raises(UserError, match=rf"record {records_copy / CELL} listed in manifest .* is missing"):
        verify_manifest(FROZEN, records_copy)
    shutil.copy(RECORDS / CELL, records_copy / CELL)
    extra = records_copy / "libero" / "libero_spatial" / "pi05" / "extra.jsonl"
    shutil.copy(RECORDS / CELL, extra)
    with pytest.raises(UserError, match=rf"record {extra} is not listed in manifest"):
        verify_manifest(FROZEN, records_copy)


def test_manifest_with_wrong_columns_is_named(tmp_path):
    bad = tmp_path / "bad.tsv"
    bad.write_text("path\tsha256\nx.jsonl\tabc\n")
    with pytest.raises(UserError, match=rf"manifest {bad}: expected columns path, episodes, successes, sha256\[, outcomes\]"):
        verify_manifest(bad, RECORDS)


def test_cli_writes_and_checks(records_copy, tmp_path, capsys):
    out = tmp_path / "manifest.tsv"
    assert main(["manifest", str(records_copy), "-o", str(out)]) == 0
    assert out.read_text() == FROZEN.read_text()
    assert main(["manifest", str(records_copy), "--check", str(FROZEN)]) == 0
    path = records_copy / CELL
    path.write_text(path.read_text() + "\n")
    assert main(["manifest", str(records_copy), "--check", str(FROZEN)]) == 2
    assert f"record {path} does not match manifest" in capsys.readouterr().err
