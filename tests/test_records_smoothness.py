"""Smoothness in every episode record (issue 31 item 6): jerk and action rate of the executed actions, their
definition, their place in the record schema, and their table statistic with a task-clustered interval."""

import hashlib

import numpy as np
import pandas as pd
import pytest

from vlaquantbench.envs.libero import LiberoSuite, LiberoVectorEnv
from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.records import read_cell, write_cell
from vlaquantbench.records.smoothness import smoothness
from vlaquantbench.runner.loop import run_episodes
from vlaquantbench.stats import task_clustered_mean
from vlaquantbench.tables.definition import TableDefinition
from vlaquantbench.tables.latex import table_rows

HEADER = {"model": "pi05", "benchmark": "libero", "suite": "libero_spatial", "seed": 0, "episodes_per_task": 2,
          "max_steps": 20}


def test_the_definition_on_sequences_whose_differences_are_known():
    steps = np.arange(8.0)[:, None]
    assert smoothness(np.ones((8, 7))) == {"action_rate": 0.0, "jerk": 0.0}
    # A ramp of slope 0.5 in two dimensions: first difference (0.5, 0.5) every step, third difference 0.
    assert smoothness(np.hstack([0.5 * steps, 0.5 * steps])) == {"action_rate": 0.5, "jerk": 0.0}
    # t^3: third difference 6 at every step; first differences 1, 7, 19, 37, 61, 91, 127.
    cubic = smoothness(steps**3)
    assert cubic["jerk"] == 36.0
    assert cubic["action_rate"] == pytest.approx(np.mean(np.square([1, 7, 19, 37, 61, 91, 127])))
    # Too short for a third difference: jerk left out, not 0; a single action has neither.
    assert smoothness(steps[:3]) == {"action_rate": 1.0}
    assert smoothness(steps[:1]) == {}
    with pytest.raises(ValueError, match="steps, action_dim"):
        smoothness(np.zeros(5))


def test_records_hold_them_optionally_and_refuse_a_negative_one(tmp_path):
    rows = [{"suite": "libero_spatial", "task_id": 0, "episode": e, "seed": e, "success": False, "steps": 20}
            for e in range(2)]
    write_cell(tmp_path / "without", HEADER, rows)  # the authors' records have none
    cell = read_cell(write_cell(tmp_path / "with", HEADER, [{**rows[0], "jerk": 0.5, "action_rate": 0.1}, rows[1]]).path)
    assert cell.episodes["jerk"].tolist()[0] == 0.5 and pd.isna(cell.episodes["jerk"].tolist()[1])
    with pytest.raises(UserError, match="jerk: -0.5 must be bigger than or equal to 0"):
        write_cell(tmp_path / "bad", HEADER, [{**rows[0], "jerk": -0.5}, rows[1]])


def test_the_task_clustered_mean_and_its_table_column(tmp_path):
    episodes = pd.DataFrame({"task_id": [0, 0, 1, 1], "episode": [0, 1, 0, 1], "jerk": [1.0, 1.0, 3.0, 3.0]})
    # Two tasks with constant values: a draw's mean is 1, 2 or 3 (both tasks picked once, or one twice).
    interval = task_clustered_mean(episodes, "jerk", draws=2000)
    assert interval.mean == 2.0 and interval.low == 1.0 and interval.high == 3.0
    tight = task_clustered_mean(episodes.assign(jerk=[1.0, 3.0, 1.0, 3.0]), "jerk", draws=2000)
    assert tight.mean == 2.0 and 1.0 <= tight.low < 2.0 < tight.high <= 3.0  # only the episodes vary

    rows = [{"suite": "libero_spatial", "task_id": t, "episode": e, "seed": 1009 * t + e, "success": False,
             "steps": 20, "jerk": float(1 + 2 * t)} for t in (0, 1) for e in (0, 1)]
    ref = "libero/libero_spatial/pi05/rtn-W4A4-ah"
    cell = write_cell(tmp_path / "cell", HEADER, rows)
    definition = TableDefinition.from_dict("smooth", {
        "caption": "x", "align": "lr", "header": [["cell", "jerk"]],
        "values": [{"stat": "mean_ci", "cell": "cell", "field": "jerk", "digits": 1}],
        "rows": [{"label": "W4A4", "cell": ref}]})
    assert table_rows(definition, {ref: cell}) == [["W4A4", "2.0 [1.0,3.0]"]]
    lacking = write_cell(tmp_path / "lacking", HEADER, [{k: v for k, v in r.items() if k != "jerk"} for r in rows])
    with pytest.raises(UserError, match="its episodes record no jerk"):
        table_rows(definition, {ref: lacking})


@pytest.mark.slow
def test_a_real_rollout_records_the_smoothness_of_exactly_its_executed_actions():
    """One demo pi0.5 episode on LIBERO: the chunks the policy returned, cut as the loop executes them, hash to
    the record's actions_sha256, so they are the executed actions, and give the recorded jerk and action rate."""
    suite = LiberoSuite("libero_spatial")
    adapter = make_adapter(AdapterConfig(model="pi05", variant="demo", flow_steps=2, executed_chunk=10))
    adapter.load()
    chunks = []
    act = adapter.act

    def recording_act(observations, generators):
        out = act(observations, generators)
        chunks.extend(np.asarray(chunk, np.float64) for chunk in out)
        return out

    adapter.act = recording_act
    records = []
    with LiberoVectorEnv(suite, 1, camera_size=64, control_mode=adapter.control_mode) as env:
        run_episodes(adapter, env, [suite.episode_spec(0, 0)], max_steps=24, on_finished=records.extend)
    (record,) = records
    assert record["steps"] == 24 and not record["success"]  # random weights: three chunks, the last cut to 4
    executed = np.concatenate([chunk[:10] for chunk in chunks])[: record["steps"]]
    assert hashlib.sha256(executed.tobytes()).hexdigest() == record["actions_sha256"]
    expected = smoothness(executed)
    assert record["jerk"] == expected["jerk"] and record["action_rate"] == expected["action_rate"]
    assert 0 < record["action_rate"] < np.inf and 0 < record["jerk"] < np.inf
