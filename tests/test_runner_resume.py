"""Cells on real LIBERO episodes: a hook that never fires; a header mismatch. (kill -9 mid-cell and the
rerun that resumes it exactly: test_runner_soak.py.)"""

import json

import pytest
from demo_study import demo_study

from vlaquantbench.cells import cell_config
from vlaquantbench.errors import UserError
from vlaquantbench.runner.cell import CellFailed, CellRun, run_cell

pytestmark = pytest.mark.slow

STUDY = demo_study(episodes_per_task=3)
REF = "libero/libero_spatial/pi05/ablate-W4A4-ah-onlyself_attn"


def journal_lines(path):
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def outcomes(folder):
    """(task, episode, seed) -> (success, steps, digest of every executed action) from the journal."""
    return {
        (r["task_id"], r["episode"], r["seed"]): (r["success"], r["steps"], r["actions_sha256"])
        for r in journal_lines(folder / "journal.jsonl")
        if r["kind"] == "episode"
    }


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
