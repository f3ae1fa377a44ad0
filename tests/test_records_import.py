"""Records: the authors' .jsonl importer and this project's cell folders, on the published records."""

import csv
import json

import pandas as pd
import pytest

from vlaquantbench.errors import UserError
from vlaquantbench.records import EPISODE_COLUMNS, find_cells, read_cell, write_cell
from paths import REFERENCE, RECORDS

HEADER = {"kind": "header", "model": "pi05", "benchmark": "libero", "suite": "libero_spatial", "seed": 0, "episodes_per_task": 20,
          "preset": "W4A4", "scope": "ah", "quant_report": {"ah": {"layers": 3, "params": 9}}}
# Task 0's name in LIBERO-Spatial: an episode's task_name must be its task id's (records.schema).
SPATIAL_TASK_0 = "pick_up_the_black_bowl_between_the_plate_and_the_ramekin_and_place_it_on_the_plate"


def episode(task_id, ep, success=True, **fields):
    return {"kind": "episode", "suite": "libero_spatial", "task_id": task_id, "episode": ep, "seed": 1009 * task_id + ep,
            "success": success, "steps": 80, "extra": {"init_state_id": ep}, **fields}  # fmt: skip


def write_jsonl(path, lines):
    path.write_text("".join((line if isinstance(line, str) else json.dumps(line)) + "\n" for line in lines))
    return path


def test_reference_cells_match_the_authors_summary():
    summary = {
        "/".join(row[k] for k in ("benchmark", "suite", "model", "cell")): row
        for row in csv.DictReader(open(REFERENCE / "authors-summary.csv", newline=""))
    }
    cells = find_cells(RECORDS)
    assert len(cells) == 65
    for ref, path in cells.items():
        cell = read_cell(path)
        assert list(cell.episodes.columns[: len(EPISODE_COLUMNS)]) == list(EPISODE_COLUMNS)
        assert (cell.n_episodes, cell.n_successes) == (int(summary[ref]["episodes"]), int(summary[ref]["successes"]))
        assert cell.header["preset"] == summary[ref]["preset"] and "kind" not in cell.header


def test_quantized_layers_come_from_the_header():
    spatial = RECORDS / "libero" / "libero_spatial" / "pi05"
    assert read_cell(spatial / "ablate-W4A4-ah-onlyself_attn.jsonl").quantized_layers == 72
    assert read_cell(spatial / "rtn-W4A4-ah.jsonl").quantized_layers == 167
    assert read_cell(spatial / "rtn-BASELINE-e2e.jsonl").quantized_layers == 0
    # act_calib entries in quant_report carry no layer count and are skipped
    assert read_cell(spatial / "calib_all_a75-W4A4-e2e.jsonl").quantized_layers == 162 + 1 + 126 + 167


def test_optional_fields_may_be_absent(tmp_path):
    path = write_jsonl(tmp_path / "cell.jsonl", [
        HEADER,
        episode(0, 0, task_name=SPATIAL_TASK_0, wall_time_s=3.5, extra={"init_state_id": 0, "subtasks_completed": 4}),
        episode(0, 1, success=False),
        {**episode(1, 0), "extra": {}},  # no init state (CALVIN/SIMPLER style)
    ])  # fmt: skip
    episodes = read_cell(path).episodes
    assert episodes["task_name"].tolist()[0] == SPATIAL_TASK_0 and pd.isna(episodes["task_name"].tolist()[1])
    assert episodes["subtasks_completed"].tolist()[0] == 4.0 and pd.isna(episodes["wall_time_s"].iloc[2])
    assert pd.isna(episodes["init_state_id"].iloc[2]) and episodes["success"].tolist() == [True, False, True]
    assert "progress_score" not in episodes


def test_truncated_line_names_file_and_line(tmp_path):
    line = json.dumps(episode(0, 1))
    path = write_jsonl(tmp_path / "cell.jsonl", [HEADER, episode(0, 0), line[: len(line) // 2]])
    with pytest.raises(UserError, match=rf"{path}:3: truncated or malformed JSON"):
        read_cell(path)


def test_duplicate_episode_key_names_file_and_lines(tmp_path):
    path = write_jsonl(tmp_path / "cell.jsonl", [HEADER, episode(0, 0), episode(0, 1), episode(0, 0, success=False)])
    with pytest.raises(UserError, match=rf"{path}:4: duplicate episode key .* \(0, 0, 0\), first on line 2"):
        read_cell(path)


@pytest.mark.parametrize("lines", [[], [episode(0, 0)], [{**HEADER, "kind": "summary"}, episode(0, 0)]])
def test_missing_header_is_an_error(tmp_path, lines):
    path = write_jsonl(tmp_path / "cell.jsonl", lines)
    with pytest.raises(UserError, match=rf"{path}:1: header line missing"):
        read_cell(path)


def test_missing_required_field_is_named(tmp_path):
    bad = episode(0, 1)
    del bad["steps"]
    path = write_jsonl(tmp_path / "cell.jsonl", [HEADER, episode(0, 0), bad])
    with pytest.raises(UserError, match=rf"{path}:3: episode lacks required field\(s\) steps"):
        read_cell(path)


def test_cell_folder_round_trip(tmp_path):
    source = read_cell(RECORDS / "libero" / "libero_spatial" / "pi05" / "rtn-W4A4-ah.jsonl")
    folder = tmp_path / "libero" / "libero_spatial" / "pi05" / "rtn-W4A4-ah"
    write_cell(folder, source.header, source.episodes)
    assert sorted(p.name for p in folder.iterdir()) == ["episodes.parquet", "header.json"]  # no temp files left
    for path in (folder, folder / "episodes.parquet"):
        cell = read_cell(path)
        assert cell.header == source.header and cell.quantized_layers == 167
        pd.testing.assert_frame_equal(cell.episodes, source.episodes)
    assert find_cells(tmp_path) == {"libero/libero_spatial/pi05/rtn-W4A4-ah": folder / "episodes.parquet"}


def test_write_cell_refuses_duplicates_and_keeps_the_old_record(tmp_path):
    source = read_cell(RECORDS / "libero" / "libero_spatial" / "pi05" / "rtn-W4A4-ah.jsonl")
    write_cell(tmp_path / "cell", source.header, source.episodes)
    before = (tmp_path / "cell" / "episodes.parquet").read_bytes()
    doubled = pd.concat([source.episodes, source.episodes.iloc[:1]])
    with pytest.raises(UserError, match="duplicate episode key"):
        write_cell(tmp_path / "cell", source.header, doubled)
    assert (tmp_path / "cell" / "episodes.parquet").read_bytes() == before


def test_folder_without_header_is_an_error(tmp_path):
    source = read_cell(RECORDS / "libero" / "libero_spatial" / "pi05" / "rtn-W4A4-ah.jsonl")
    write_cell(tmp_path / "cell", source.header, source.episodes)
    (tmp_path / "cell" / "header.json").unlink()
    with pytest.raises(UserError, match=r"header.json is missing"):
        read_cell(tmp_path / "cell" / "episodes.parquet")


def test_header_without_episodes_is_an_error(tmp_path):
    path = write_jsonl(tmp_path / "cell.jsonl", [HEADER])
    with pytest.raises(UserError, match=rf"{path}: the cell has no episodes"):
        read_cell(path)
