"""The sequential stopping rule live in the runner (issue 32, `study.sequential`): a demo cell tested against
its baseline's real records stops once the test decides, records the decision, resumes to the same decision
without running more episodes, and a stopped record passes the record checks while a truncated one does not."""

import json

import numpy as np
import pytest
from demo_study import demo_study

from vlaquantbench.cells import CellConfig, cell_config
from vlaquantbench.errors import UserError
from vlaquantbench.records import check_declared_episodes, read_cell, write_cell
from vlaquantbench.envs.episodes import EpisodeSpec
from vlaquantbench.runner.cell import CellRun, run_cell
from vlaquantbench.runner.stopping import StoppingRule
from vlaquantbench.sequential import Design, paired_rounds, stopping_rule

BASELINE = "libero/libero_spatial/pi05/rtn-BASELINE-e2e"
CELL = "libero/libero_spatial/pi05/rtn-W4A4-ah"
# Random-weight demo policies never succeed, so every paired difference is 0: with a 80 pp margin at
# alpha 0.3 the not-worse test crosses 1/alpha after 3 rounds of the one task (of a cap of 5).
STUDY = demo_study(episodes_per_task=5, max_steps=4, sequential={"alpha": 0.3, "margin_pp": 80})


def _journal_episodes(folder):
    """The journal's episode lines, in the order they finished."""
    return [r for r in map(json.loads, (folder / "journal.jsonl").read_text().splitlines()) if r["kind"] == "episode"]


@pytest.fixture(scope="module")
def baseline(tmp_path_factory):
    cfg = cell_config(BASELINE, STUDY)
    assert "sequential" not in cfg  # the cell tested against runs in full
    folder = tmp_path_factory.mktemp("baseline")
    return run_cell(cfg, folder, progress=False, num_envs=1)


@pytest.mark.slow
def test_a_sequential_cell_stops_when_decided_and_resumes_without_more_episodes(baseline, tmp_path):
    cfg = cell_config(CELL, STUDY)
    assert cfg["sequential"]["against"]["ref"] == BASELINE
    with pytest.raises(UserError, match="rtn-BASELINE-e2e, whose records were not given"):
        run_cell(cfg, tmp_path / "no_baseline", progress=False)

    folder = tmp_path / "cell"
    run_cell(cfg, folder, progress=False, num_envs=2, against_records=baseline)
    cell = check_declared_episodes(read_cell(folder))
    stopping = cell.header["stopping"]
    # Two workers on one task: batches of two rounds, so the decision at round 3 ran round 4 too.
    assert stopping["decision"] == "not_worse" and stopping["rounds_used"] == 3 and stopping["episodes_used"] == 3
    assert stopping["rounds_run"] == 4 and len(cell.episodes) == 4 and stopping["against"] == BASELINE
    # The recorded state is the test's on these records.
    expected = stopping_rule(paired_rounds(cell.episodes, read_cell(baseline).episodes.iloc[:4]), Design(0.3, 80))
    assert (expected.decision, expected.rounds_used) == ("not_worse", 3)
    assert stopping["log_capital_not_worse"] == pytest.approx(expected.log_capital_not_worse)
    assert stopping["log_capital_not_worse"] >= np.log(1 / 0.3) > stopping["log_capital_worse"]

    journal = (folder / "journal.jsonl").read_text()
    rerun = CellRun(cfg, folder, progress=False, num_envs=2, against_records=baseline)
    rerun.start_env()
    assert rerun._env is None  # the journal holds the decision: no LIBERO worker starts
    rerun.prepare()
    rerun.run()  # and no episode runs
    assert (folder / "journal.jsonl").read_text() == journal

    # Killed after its first episode: the resumed cell decides the same, from the same episodes.
    resumed = tmp_path / "resumed"
    resumed.mkdir()
    lines = journal.splitlines(keepends=True)
    first_episode = next(n for n, line in enumerate(lines) if json.loads(line)["kind"] == "episode")
    (resumed / "journal.jsonl").write_text("".join(lines[: first_episode + 1]))
    run_cell(cfg, resumed, progress=False, num_envs=1, against_records=baseline)
    again = read_cell(resumed)
    assert again.header["stopping"] == {**stopping, "rounds_run": 3}  # one worker: it stops right at round 3
    digests = {e["episode"]: e["actions_sha256"] for e in _journal_episodes(folder)}
    assert {e["episode"]: e["actions_sha256"] for e in _journal_episodes(resumed)} == {k: digests[k] for k in range(3)}


@pytest.mark.slow
def test_a_short_record_is_complete_only_with_its_stop_decision(baseline, tmp_path):
    base = read_cell(baseline)
    header = {**base.header, "stopping": {
        "decision": "worse", "rounds_used": 2, "episodes_used": 2, "rounds_run": 3, "log_capital_worse": 3.1,
        "log_capital_not_worse": 0.0, "alpha": 0.05, "margin_pp": 5.0, "against": BASELINE}}
    first_three = base.episodes[base.episodes["episode"] < 3]
    check_declared_episodes(write_cell(tmp_path / "stopped", header, first_three))
    truncated = write_cell(tmp_path / "truncated", base.header, first_three)  # no stop decision: a gap
    with pytest.raises(UserError, match="task 0 lacks episode\\(s\\) 3, 4"):
        check_declared_episodes(truncated)
    short = write_cell(tmp_path / "short", header, base.episodes[base.episodes["episode"] < 2])
    with pytest.raises(UserError, match="task 0 lacks episode\\(s\\) 2"):
        check_declared_episodes(short)
    with pytest.raises(UserError, match="stopping.decision"):
        write_cell(tmp_path / "bad", {**header, "stopping": {**header["stopping"], "decision": "better"}}, first_three)


def test_bad_sequential_settings_are_refused_naming_the_field():
    with pytest.raises(UserError, match="study.sequential.against: .*name 'baseline' does not follow"):
        cell_config(CELL, demo_study(sequential={"against": "baseline"}))
    with pytest.raises(UserError, match="study.sequential.alpha: 1.5"):
        cell_config(CELL, demo_study(sequential={"alpha": 1.5}))
    with pytest.raises(UserError, match="study.sequential: unknown key .max_episodes."):
        cell_config(CELL, demo_study(sequential={"max_episodes": 100}))
    # Off, a cell's canonical config (hence its folder) is the fixed design's, as before the option existed.
    assert cell_config(CELL, demo_study()) == cell_config(CELL, demo_study(sequential=None))
    assert "sequential" not in cell_config(CELL, demo_study())


def _outcomes(tasks, episodes, success):
    return [{"suite": "libero_spatial", "task_id": t, "episode": e, "seed": 1009 * t + e, "init_state_id": e,
             "success": success, "steps": 4} for e in episodes for t in tasks]


def test_batches_fill_the_workers_and_a_decided_cell_only_completes_its_rounds(tmp_path):
    """Two tasks, a cap of 8 rounds, a baseline that always succeeds and a cell that never does: `worse` at
    round 5. Four workers run batches of two rounds; the decision inside a batch completes only its rounds."""
    header = {"model": "pi05", "benchmark": "libero", "suite": "libero_spatial", "seed": 0, "episodes_per_task": 8,
              "tasks": [0, 1], "config_hash": "0123456789ab"}
    baseline = write_cell(tmp_path / "baseline", header, _outcomes([0, 1], range(8), True)).path
    fields = {"tasks": [0, 1], "episodes_per_task": 8,
              "sequential": {"alpha": 0.05, "margin_pp": 5.0, "against": {"ref": BASELINE, "config_hash": "0123456789ab"}}}

    def typed(**changed):  # the demo cell's typed config with the fields this test sets
        return CellConfig.from_dict({**cell_config(CELL, STUDY), **fields, **changed})

    rule = StoppingRule(typed(), baseline)
    specs = [EpisodeSpec(t, e, e, 1009 * t + e) for e in range(8) for t in (0, 1)]

    def missing(done):
        keys = {(d["task_id"], d["episode"]) for d in done}
        return [s for s in specs if (s.task_id, s.episode) not in keys]

    def keys(batch):
        return [(s.task_id, s.episode) for s in batch]

    assert keys(rule.next_batch([], specs, 4)) == keys(specs[:4])
    done = _outcomes([0, 1], range(4), False)
    assert rule.result(done) is None and keys(rule.next_batch(done, missing(done), 4)) == keys(specs[8:12])
    done += _outcomes([0, 1], [4], False) + _outcomes([0], [5], False)  # round 5 begun: the test decided at it
    assert rule.result(done).decision == "worse"
    assert keys(rule.next_batch(done, missing(done), 4)) == [(1, 5)]
    with pytest.raises(UserError, match="has not finished \\(5 complete rounds of 6 begun"):
        rule.outcome(done)
    done += _outcomes([1], [5], False)
    assert rule.next_batch(done, missing(done), 4) == []
    outcome = rule.outcome(done)
    assert (outcome["decision"], outcome["rounds_used"], outcome["episodes_used"], outcome["rounds_run"]) == (
        "worse", 5, 10, 6)

    # A cell as good as its baseline cannot be called within 5 pp in 8 rounds: it runs to the cap, undecided.
    equal = _outcomes([0, 1], range(7), True)
    assert rule.result(equal) is None and keys(rule.next_batch(equal, missing(equal), 4)) == keys(specs[14:])
    assert rule.outcome(_outcomes([0, 1], range(8), True))["decision"] == "undecided"

    with pytest.raises(UserError, match="config hash '0123456789ab', but cell .* with config hash 'ffffffffffff'"):
        StoppingRule(typed(sequential={**fields["sequential"], "against": {"ref": BASELINE, "config_hash": "ffffffffffff"}}),
                     baseline)
    with pytest.raises(UserError, match="fewer than 9 episodes on some task"):
        StoppingRule(typed(episodes_per_task=9), baseline)
