"""Non-finite actions on real LIBERO: they never reach MuJoCo, the episode is flagged, the header counts
it and a table can show the count."""

import hashlib
import json

import numpy as np
import pytest
from demo_study import demo_study

from vlaquantbench.cells import cell_config
from vlaquantbench.envs.libero import LiberoSuite, LiberoVectorEnv
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.records import read_cell
from vlaquantbench.runner.cell import CellRun
from vlaquantbench.runner.loop import run_episodes
from vlaquantbench.tables.definition import TableDefinition
from vlaquantbench.tables.latex import table_rows

pytestmark = pytest.mark.slow

STUDY = demo_study(episodes_per_task=2)
REF = "libero/libero_spatial/pi05/rtn-BASELINE-e2e"


def test_a_policy_with_nan_weights_is_flagged_counted_and_tabulated(tmp_path, capfd):
    run = CellRun(cell_config(REF, STUDY), tmp_path, num_envs=2, progress=False)
    run.prepare()
    run.adapter.model.action_out_proj.weight.data.fill_(float("nan"))  # a collapsed policy: every action NaN
    run.run()

    cell = read_cell(tmp_path)
    assert cell.header["nonfinite_episodes"] == 2 and cell.n_nonfinite == 2
    assert cell.episodes["nonfinite_action"].all() and not cell.episodes["success"].any()
    assert (cell.episodes["steps"] == 0).all()  # the first action was already NaN: nothing was stepped
    journal = [json.loads(line) for line in (tmp_path / "journal.jsonl").read_text().splitlines()]
    assert [e["actions_sha256"] for e in journal if e["kind"] == "episode"] == [hashlib.sha256().hexdigest()] * 2
    assert "2 of 2 episodes ended on a non-finite action" in capfd.readouterr().err

    table = TableDefinition.from_dict("t", {
        "caption": "c", "align": "lrr", "header": [["", "SR", "NaN"]],
        "values": [{"stat": "rate", "cell": "cell"}, {"stat": "nonfinite", "cell": "cell"}],
        "rows": [{"label": "baseline", "cell": REF}],
    })
    assert table_rows(table, {REF: cell}) == [["baseline", "0.0", "2"]]


def test_a_nan_midway_through_a_chunk_ends_the_episode_before_it():
    suite = LiberoSuite("libero_spatial")
    adapter = make_adapter(AdapterConfig(model="pi05", variant="demo", flow_steps=2))
    adapter.load()
    act, executed = adapter.act, []

    def nan_in_second_chunk(observations, generators):
        chunks = act(observations, generators)
        if executed:
            chunks[0, 4, 2] = np.nan  # the 5th action of the second chunk
        executed.extend(np.asarray(chunks[0, : adapter.executed_chunk], np.float64))
        return chunks

    adapter.act = nan_in_second_chunk
    records = []
    with LiberoVectorEnv(suite, 1, camera_size=64) as env:
        run_episodes(adapter, env, [suite.episode_spec(0, 0)], max_steps=30, on_finished=records.extend)
    (record,) = records
    assert (record["steps"], record["success"], record["nonfinite_action"]) == (14, False, True)
    assert record["actions_sha256"] == hashlib.sha256(np.stack(executed[:14]).tobytes()).hexdigest()
