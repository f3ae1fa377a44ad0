"""Records are checked against the episode schema their header bounds: a fault is refused on its own line
(authors' .jsonl), row (a cell folder's episodes.parquet) or journal line, before any table is written."""

import importlib
import json
import re
import shutil

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from vlaquantbench.errors import UserError
from vlaquantbench.records import find_cells, read_cell, write_cell
from vlaquantbench.records.summary import read_summary
from vlaquantbench.runner.journal import CellJournal
from vlaquantbench.tables import load_table
from vlaquantbench.tables.latex import read_cells
from paths import REFERENCE, ROOT, RECORDS

# tab:lattice's all-167-layer row: 141 of 200 successes (70.5); one string "false" made it 71.0.
LATTICE_CELL = "libero/libero_spatial/pi05/rtn-W4A4-ah"
SEED_RECORDS = REFERENCE / "seed-records"


@pytest.fixture
def jsonl(tmp_path):
    """A writable copy of the reference cell and its lines."""
    path = tmp_path / "rtn-W4A4-ah.jsonl"
    shutil.copyfile(RECORDS / f"{LATTICE_CELL}.jsonl", path)
    return path


def lines_of(path):
    return path.read_text().splitlines()


def write_lines(path, lines):
    path.write_text("\n".join(lines) + "\n")
    return path


def task_12(line):
    """An episode line of task 12 (absent from the 10-task LIBERO-Spatial), its seed following the protocol."""
    record = json.loads(line)
    record.update(task_id=12, seed=1009 * 12 + record["episode"])
    return json.dumps(record)


def test_a_string_success_is_refused_naming_file_and_line(jsonl):
    lines = lines_of(jsonl)
    number = next(i for i, line in enumerate(lines) if '"success": false' in line)
    lines[number] = lines[number].replace('"success": false', '"success": "false"')
    write_lines(jsonl, lines)
    with pytest.raises(UserError, match=rf"^{jsonl}:{number + 1}: success: 'false' must be boolean$"):
        read_cell(jsonl)
    # what the table reads goes through the same check: the row cannot move from 70.5 to 71.0
    definition = load_table(ROOT / "config" / "tables" / "lattice.yaml")
    with pytest.raises(UserError, match=rf"{jsonl}:{number + 1}: success"):
        read_cells(definition.refs(), {LATTICE_CELL: jsonl})


def test_an_appended_episode_of_task_12_is_refused_naming_its_line(jsonl):
    lines = lines_of(jsonl)
    write_lines(jsonl, [*lines, task_12(lines[-1])])
    with pytest.raises(UserError, match=rf"^{jsonl}:{len(lines) + 1}: task_id: 12 must be smaller than or equal to 9 "
                                        r"\(libero_spatial has 10 tasks: 0\.\.9\)$"):  # fmt: skip
        read_cell(jsonl)


def test_an_episode_replaced_by_one_of_task_12_is_refused_naming_its_line(jsonl):
    lines = lines_of(jsonl)
    lines[57] = task_12(lines[57])  # task 2, episode 16: before, only "task 2 lacks episode(s) 16" said anything
    write_lines(jsonl, lines)
    with pytest.raises(UserError, match=rf"^{jsonl}:58: task_id: 12 must be smaller than or equal to 9"):
        read_cell(jsonl)


@pytest.mark.parametrize(
    ("field", "value", "problem"),
    [
        ("suite", "libero_goal", r"suite: 'libero_goal' must be same as const definition: libero_spatial \(the header's suite\)"),
        ("steps", 281, r"steps: 281 must be smaller than or equal to 280 \(the step limit of pi05 on libero_spatial\)"),
        ("episode", 20, r"episode: 20 must be smaller than or equal to 19 \(the header declares 20 episodes per task\)"),
        ("seed", 7, r"seed: 7 is not the protocol's 1009 \* task_id \+ episode \+ 1000003 \* run seed = 2034"),
        ("init_state_id", 3, r"init_state_id: 3 is not the episode index 16"),
        ("steps", 80.5, r"steps: 80\.5 must be integer"),
    ],
)  # fmt: skip
def test_each_episode_field_is_checked_against_the_header_and_protocol(jsonl, field, value, problem):
    lines = lines_of(jsonl)
    record = json.loads(lines[57])  # task 2, episode 16
    (record["extra"] if field == "init_state_id" else record)[field] = value
    lines[57] = json.dumps(record)
    write_lines(jsonl, lines)
    with pytest.raises(UserError, match=rf"^{jsonl}:58: {problem}"):
        read_cell(jsonl)


def test_a_header_without_its_suite_is_refused_naming_the_header_line(jsonl):
    lines = lines_of(jsonl)
    header = json.loads(lines[0])
    del header["suite"]
    write_lines(jsonl, [json.dumps(header), *lines[1:]])
    with pytest.raises(UserError, match=rf"^{jsonl}:1: run header: lacks required field\(s\) suite$"):
        read_cell(jsonl)


@pytest.fixture
def folder(tmp_path):
    """The reference cell as this project's cell folder."""
    source = read_cell(RECORDS / f"{LATTICE_CELL}.jsonl")
    write_cell(tmp_path / "cell", source.header, source.episodes)
    return tmp_path / "cell"


def rewrite_parquet(folder, change):
    path = folder / "episodes.parquet"
    frame = pq.read_table(path).to_pandas()
    pq.write_table(pa.Table.from_pandas(change(frame), preserve_index=False), path)
    return path


def test_a_string_success_column_in_parquet_is_refused_naming_row_and_episode(folder):
    path = rewrite_parquet(folder, lambda frame: frame.assign(success=frame["success"].map({True: "true", False: "false"})))
    with pytest.raises(UserError, match=rf"^{path} row 1 \(task 0, episode 0, seed 0\): success: 'true' must be boolean$"):
        read_cell(folder)


def test_a_parquet_row_of_task_12_is_refused_naming_row_and_episode(folder):
    def replace_row_57(frame):  # task 2, episode 16
        frame.loc[56, ["task_id", "seed"]] = [12, 1009 * 12 + 16]
        return frame

    path = rewrite_parquet(folder, replace_row_57)
    with pytest.raises(UserError, match=rf"^{path} row 57 \(task 12, episode 16, seed 12124\): task_id: 12 must be smaller"):
        read_cell(folder)


def test_a_corrupt_parquet_is_refused_naming_the_file(folder):
    path = folder / "episodes.parquet"
    path.write_bytes(path.read_bytes()[:500])
    with pytest.raises(UserError, match=rf"^{path}: not a readable parquet file \("):
        read_cell(folder)


def test_write_cell_refuses_a_bad_episode_and_writes_nothing(tmp_path):
    source = read_cell(RECORDS / f"{LATTICE_CELL}.jsonl")
    bad = source.episodes.astype({"success": "object"})
    bad.loc[3, "success"] = "false"
    with pytest.raises(UserError, match=r"episodes.parquet row 4 \(task 0, episode 3, seed 3\): success: 'false' must be boolean"):
        write_cell(tmp_path / "cell", source.header, bad)
    assert not (tmp_path / "cell").exists()


def test_a_cell_read_under_another_ref_is_refused(tmp_path):
    shutil.copyfile(RECORDS / f"{LATTICE_CELL}.jsonl", tmp_path / "a.jsonl")
    ref = "libero/libero_object/pi05/rtn-W4A4-ah"  # a spatial record filed as an object cell
    with pytest.raises(UserError, match=rf"{tmp_path / 'a.jsonl'}: its header says suite 'libero_spatial', but it is read as cell {ref}"):
        read_cells([ref], {ref: tmp_path / "a.jsonl"})


def test_a_journal_episode_of_task_12_is_refused_naming_the_journal_line(tmp_path):
    header = {"model": "pi05", "benchmark": "libero", "suite": "libero_spatial", "seed": 0, "episodes_per_task": 2,
              "config": {"tasks": [0, 1]}}  # fmt: skip
    path = tmp_path / "journal.jsonl"
    journal = CellJournal(path, header)
    episode = {"suite": "libero_spatial", "task_id": 0, "episode": 1, "seed": 1, "init_state_id": 1, "success": True, "steps": 30}
    journal.record([episode], fired=set())
    with open(path, "a") as handle:
        handle.write(json.dumps({"kind": "episode", **episode, "task_id": 12, "seed": 12109}) + "\n")
    with pytest.raises(UserError, match=rf"^{path}:3: task_id: 12 must be one of \[0, 1\] \(the tasks the header lists\)$"):
        CellJournal(path, header)


def test_the_reference_records_pass_unchanged():
    frames = [read_cell(path).episodes for path in sorted(RECORDS.rglob("*.jsonl"))]
    assert len(frames) == 65 and sum(map(len, frames)) == 12980
    assert all(frame["success"].dtype == bool for frame in frames)
    assert pd.concat(frames)["success"].sum() > 0


def test_the_published_seed_repeats_pass_in_place_with_the_authors_counts():
    """The authors' run seeds 1 and 2 of the pi0.5 Object baseline: every episode has the protocol's seed, and each
    cell's counts are its row of the authors' summary."""
    summary = read_summary(REFERENCE / "authors-summary.csv")
    cells = find_cells(SEED_RECORDS)
    assert list(cells) == [f"libero/libero_object/pi05/seed{run_seed}-rtn-BASELINE-e2e" for run_seed in (1, 2)]
    for run_seed, (ref, path) in enumerate(cells.items(), start=1):
        cell = read_cell(path)
        assert cell.header["seed"] == run_seed and cell.n_episodes == 200
        assert (cell.n_episodes, cell.n_successes) == (summary[ref].n_episodes, summary[ref].n_successes)
        seeds = cell.episodes.set_index(["task_id", "episode"])["seed"]
        assert seeds[0, 0] == 1_000_003 * run_seed and seeds[1, 0] == 1009 + 1_000_003 * run_seed


def test_a_run_seed_1_episode_with_the_old_offset_is_refused(tmp_path):
    """Run seed 1 used to add 1 to every episode seed: such a record names its line and the protocol's seed."""
    source = SEED_RECORDS / "libero/libero_object/pi05/seed1-rtn-BASELINE-e2e.jsonl"
    path = tmp_path / source.name
    lines = lines_of(source)
    record = json.loads(lines[22])  # task 1, episode 1
    lines[22] = json.dumps({**record, "seed": 1009 + 1 + 1})
    write_lines(path, lines)
    with pytest.raises(UserError, match=rf"^{path}:23: seed: 1011 is not the protocol's 1009 \* task_id \+ episode \+ "
                                        r"1000003 \* run seed = 1001013 \(task 1, episode 1, run seed 1\)$"):  # fmt: skip
        read_cell(path)


def truncated(source, tmp_path):
    """A copy of `source` cut in half, as a full disk or a killed copy leaves it."""
    path = tmp_path / source.name
    path.write_bytes(source.read_bytes()[: source.stat().st_size // 2])
    return path


@pytest.mark.parametrize(
    ("read", "source"),
    [
        ("vlaquantbench.records.summary:read_summary", REFERENCE / "authors-summary.csv"),
        ("vlaquantbench.diagnostics.files:Diagnostics.read", REFERENCE / "authors-files" / "diagnostics" / "v2" / "pi05-ah-W4A4.json"),
        ("vlaquantbench.replay.run:ReplayRun.load", REFERENCE / "authors-files" / "results" / "replay" / "pi05_spatial" / "W4" / "analysis.json"),
    ],
)  # fmt: skip
def test_an_unreadable_input_of_a_table_names_its_file(tmp_path, read, source):
    module, name = read.split(":")
    reader = importlib.import_module(module)
    for part in name.split("."):
        reader = getattr(reader, part)
    path = truncated(source, tmp_path)
    if path.suffix == ".csv":  # half a CSV still parses: binary garbage after its header line instead
        path.write_bytes(b"benchmark,suite\n\xff\xfe\x00")
    with pytest.raises(UserError, match=re.escape(str(path))):
        reader(path)
