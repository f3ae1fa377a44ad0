"""The episode-seed protocol (`envs.episodes.episode_seed`) on every benchmark: the authors' seeds at any run seed,
evaluation-seed repeats that are repeats, and run seed 0's cells unchanged (no simulator steps)."""

import json

import pytest

from vlaquantbench.cells import calibration_config, cell_config, config_hash, hashed_config
from vlaquantbench.envs import BENCHMARK_SUITES, make_suite
from vlaquantbench.envs.episodes import RUN_SEED_STRIDE
from vlaquantbench.records import find_cells, read_cell
from paths import REFERENCE, ROOT

SEED_RECORDS = REFERENCE / "seed-records"
# This project's committed cells (all of run seed 0), hashed and recorded before the protocol took the run-seed stride.
COMMITTED = [ROOT / "results" / "methods_2026", ROOT / "results" / "trained_sequential" / "fixed",
             ROOT / "results" / "trained_sequential" / "live"]  # fmt: skip
STUDY = {"models": {"pi05": {"variant": "demo"}}, "tasks": [0], "episodes_per_task": 2,
         "calibration": {"tasks": 1, "episodes": 2}}  # fmt: skip


def test_episode_specs_reproduce_the_published_seed_repeats():
    """Every episode of the authors' run seeds 1 and 2 (pi0.5, LIBERO-Object) is the spec the runner would run."""
    suite = make_suite("libero", "libero_object")
    assert [suite.episode_spec(t, 0, s).seed for t, s in ((0, 1), (1, 1), (0, 2))] == [1_000_003, 1_001_012, 2_000_006]
    for path in find_cells(SEED_RECORDS).values():
        cell = read_cell(path)
        run_seed = cell.header["seed"]
        recorded = cell.episodes[["task_id", "episode", "init_state_id", "seed"]].itertuples(index=False)
        assert [(spec.init_state_id, spec.seed) for spec in suite.episodes(20, run_seed=run_seed)] == [
            (row.init_state_id, row.seed) for row in recorded]


@pytest.mark.parametrize(("benchmark", "suite_name"), [("libero", "libero_spatial"), ("metaworld", "metaworld_easy")])
def test_run_seeds_repeat_the_scenes_with_seeds_no_other_run_seed_has(benchmark, suite_name):
    """Over a suite's every task and init state (or variation): each run seed starts the same scenes, and no
    episode seed of one run seed recurs in another."""
    suite = make_suite(benchmark, suite_name)
    per_task = BENCHMARK_SUITES[benchmark][suite_name].init_states
    runs = {run_seed: suite.episodes(per_task, run_seed=run_seed) for run_seed in (0, 1, 2)}
    scenes = {run_seed: [(spec.task_id, spec.init_state_id) for spec in specs] for run_seed, specs in runs.items()}
    assert scenes[0] == scenes[1] == scenes[2]
    seeds = [spec.seed for specs in runs.values() for spec in specs]
    assert len(set(seeds)) == len(seeds) == 3 * suite.n_tasks * per_task


def test_meta_world_variations_are_the_ones_the_demonstrations_recorded():
    """The committed demonstrations (variations 500 on, run seed 0) drew each placement from the seed recorded
    with it: the suite still gives those seeds."""
    demonstrations = json.loads((ROOT / "benchmarks" / "results" / "trained_cpu" / "demonstrations.json").read_text())
    suite = make_suite("metaworld", demonstrations["settings"]["suite"])
    recorded = [(task["task"], episode["variation"], episode["variation_seed"])
                for task in demonstrations["tasks"] for episode in task["episodes"]]  # fmt: skip
    assert len(recorded) == 60
    assert [suite.variation_seed(suite.task_id(name), variation) for name, variation, _ in recorded] == [
        seed for _, _, seed in recorded]


def test_run_seed_0_cells_keep_their_hashes_and_episodes():
    """Each committed cell's header hash is still its config's hash, and its episodes still pass the record
    check, which compares every episode's seed with the protocol's."""
    headers = 0
    for records in COMMITTED:
        for ref, path in find_cells(records).items():
            cell = read_cell(path)
            assert cell.header["seed"] == 0 and config_hash(cell.header["config"]) == cell.header["config_hash"], ref
            headers += 1
    assert headers == 27


def test_a_cell_or_calibration_of_another_run_seed_hashes_the_run_seed_stride():
    """Its episodes differ from those that run seed had before the stride, so its hash, folder and statistics do."""
    ref = "libero/libero_spatial/pi05/{}calib_ah-W4A4-ah"
    for run_seed, prefix in ((0, ""), (1, "seed1-"), (2, "seed2-")):
        cfg = cell_config(ref.format(prefix), STUDY)
        expected = {"run_seed_stride": RUN_SEED_STRIDE} if run_seed else {}
        for hashed in (hashed_config(cfg), hashed_config(calibration_config(cfg))):
            assert {k: v for k, v in hashed.items() if k == "run_seed_stride"} == expected, run_seed
