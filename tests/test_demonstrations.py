"""Rule demonstrations (issue 30): a real `snakemake` run of Meta-World's scripted experts on two tasks at
32 pixels writes a LeRobotDataset that lerobot reads back, keeps only successful episodes, counts every
attempt, and lists every file in a SHA-256 manifest; the demonstrations' task variations are never
ones that closed-loop evaluation starts from.

The failed episode is real: the step limit is set to 45, so reach-v3's expert fails on variation 500
(it needs 51 steps there, measured with metaworld 3.0.0) and succeeds on 501 (44 steps), while
handle-press-v3 succeeds on 500 (32 steps). The run is `demonstrations_run` (conftest.py), which also trains
on the dataset (tests/test_training.py reads that)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from demonstrations_workflow import EXPERTS, TASKS
from vlaquantbench.config.study import StudyConfig
from vlaquantbench.demonstrations import (
    DATASET_DIR,
    MANIFEST_FILE,
    SUMMARY_FILE,
    DemonstrationConfig,
    check_disjoint_from_evaluation,
    write_demonstrations,
)
from vlaquantbench.envs import make_env, make_suite
from vlaquantbench.envs.metaworld import lerobot_metaworld_config
from vlaquantbench.errors import UserError
from vlaquantbench.manifest import read_manifest, verify_file_manifest

pytestmark = pytest.mark.slow

EVALUATION_EPISODES = 50  # lerobot-eval's n_episodes per task, the most a Meta-World study here evaluates


@pytest.fixture(scope="module")
def demos(demonstrations_run):
    """The rule's outputs from `snakemake --cores 2 results/demos/manifest.tsv` in a fresh working folder."""
    out = demonstrations_run["out"]
    return {"out": out,
            "summary": json.loads((out / SUMMARY_FILE).read_text())}


def test_only_successful_expert_episodes_are_kept_and_every_attempt_is_counted(demos):
    tasks = {t["task"]: t for t in demos["summary"]["tasks"]}
    assert [(t["task"], t["tried"], t["kept"]) for t in demos["summary"]["tasks"]] == [
        ("reach-v3", 2, 1), ("handle-press-v3", 1, 1)]
    failed, solved = tasks["reach-v3"]["episodes"]
    assert (failed["variation"], failed["success"], failed["steps"], failed["dataset_episode"]) == (500, False, 45, None)
    assert (solved["variation"], solved["success"], solved["dataset_episode"]) == (501, True, 1)
    # Round 1 tried variation 500 of both tasks; round 2 replaced reach-v3's failure with variation 501.
    assert tasks["handle-press-v3"]["episodes"][0]["dataset_episode"] == 0
    # Seeds recorded: each variation's seed is the one Meta-World drew its placement from.
    task_ids = lerobot_metaworld_config()["TASK_NAME_TO_ID"]
    assert solved["variation_seed"] == 1009 * task_ids["reach-v3"] + 501


def test_lerobot_reads_the_dataset_back_as_the_env_rendered_it(demos):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    summary = demos["summary"]
    dataset = LeRobotDataset(summary["dataset"]["repo_id"], root=demos["out"] / DATASET_DIR)
    kept = sorted((e for t in summary["tasks"] for e in t["episodes"] if e["dataset_episode"] is not None),
                  key=lambda e: e["dataset_episode"])
    assert dataset.num_episodes == 2
    assert dataset.meta.fps == 80  # lerobot's MetaworldEnv
    assert dataset.num_frames == sum(e["steps"] for e in kept) == 32 + 44
    descriptions = lerobot_metaworld_config()["TASK_DESCRIPTIONS"]
    first = {}
    for index in range(dataset.num_frames):
        frame = dataset[index]
        assert frame["observation.image"].shape == (3, 32, 32)
        assert frame["observation.state"].shape == frame["action"].shape == (4,)
        assert frame["action"].abs().max() <= 1
        first.setdefault(int(frame["episode_index"]), frame)
    assert [first[i]["task"] for i in (0, 1)] == [descriptions["handle-press-v3"], descriptions["reach-v3"]]

    # Frame 0 of each episode is what the closed loop's env shows at the reset of that variation.
    suite = make_suite("metaworld", "metaworld_mt50")
    specs = [suite.episode_spec(suite.task_id(task), e["variation"]) for task, e in
             (("handle-press-v3", kept[0]), ("reach-v3", kept[1]))]
    with make_env("metaworld", suite, 2, camera_size=32) as env:
        observations = env.reset(specs)
    for episode, observation in enumerate(observations):
        image = (first[episode]["observation.image"] * 255).round().byte().permute(1, 2, 0).numpy()
        assert np.array_equal(image, observation["image"])
        np.testing.assert_allclose(first[episode]["observation.state"].numpy(), observation["state"], rtol=1e-6)


def test_the_manifest_lists_every_file_and_catches_a_change(demos):
    out = demos["out"]
    rows = verify_file_manifest(out / MANIFEST_FILE, out)
    assert {r.path for r in rows} >= {SUMMARY_FILE, f"{DATASET_DIR}/meta/info.json",
                                      f"{DATASET_DIR}/data/chunk-000/file-000.parquet"}
    # Every file but the manifest and Snakemake's timestamp of the directory output.
    assert set(read_manifest(out / MANIFEST_FILE)) == {p.relative_to(out).as_posix() for p in out.rglob("*")
                                                       if p.is_file() and p.name not in (MANIFEST_FILE, ".snakemake_timestamp")}


def test_a_changed_dataset_file_fails_verification(demos, tmp_path):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(demos["out"], copy)
    info = copy / DATASET_DIR / "meta" / "info.json"
    info.write_text(info.read_text().replace('"fps": 80', '"fps": 81'))
    with pytest.raises(UserError, match=r"meta/info.json does not match manifest .*SHA-256 differs"):
        verify_file_manifest(copy / MANIFEST_FILE, copy)


def test_demonstration_variations_are_never_evaluated(demos):
    """Every attempted demonstration drew a placement that no evaluation episode 0..49 of its task draws."""
    suite = make_suite("metaworld", "metaworld_mt50")
    task_ids = [suite.task_id(t) for t in TASKS]
    with make_env("metaworld", suite, 2, camera_size=None) as env:
        evaluated = []
        specs = suite.episodes(EVALUATION_EPISODES, task_ids=task_ids)
        for start in range(0, len(specs), env.num_envs):
            batch = specs[start : start + env.num_envs]
            evaluated += [(s.task_id, o["task_variation"]) for s, o in zip(batch, env.reset(batch))]
    for task in demos["summary"]["tasks"]:
        for episode in task["episodes"]:
            assert episode["variation"] >= EVALUATION_EPISODES
            placements = [v for t, v in evaluated if suite.task(t).name == task["task"]]
            assert len(placements) == EVALUATION_EPISODES
            assert not any(np.allclose(episode["task_variation"], v) for v in placements)


def test_a_study_evaluating_a_demonstration_variation_is_refused():
    config = DemonstrationConfig.from_dict({**EXPERTS, "tasks": TASKS, "first_variation": 20})

    def study(episodes: int, first_calibration: int) -> StudyConfig:
        return StudyConfig.from_dict({"models": {"pi05": {"variant": "demo"}}, "episodes_per_task": episodes,
                                      "calibration": {"first_init_state": first_calibration, "episodes": 2}})

    check_disjoint_from_evaluation(config, study(20, 400))  # variations 0..19 and 400..401
    with pytest.raises(UserError, match=r"meet the variations 0\.\.20 \(study.episodes_per_task 21: evaluation "
                                        r"episode e starts from variation e\) at 20\.\.20"):
        check_disjoint_from_evaluation(config, study(21, 400))
    with pytest.raises(UserError, match=r"meet the variations 118\.\.119 \(study.calibration.first_init_state 118, "
                                        r"episodes 2\) at 118\.\.119"):
        check_disjoint_from_evaluation(config, study(20, 118))


@pytest.mark.parametrize(("section", "message"), [
    ({**EXPERTS, "tasks": TASKS, "image_size": 8}, r"demonstrations.image_size: 8 is less than the minimum of 16"),
    ({**EXPERTS, "tasks": TASKS, "episodes": 3},
     r"workflow config: demonstrations: unknown key 'episodes'; allowed keys: benchmark, dir, episodes_per_task"),
    ({**EXPERTS, "tasks": []}, r"demonstrations.tasks: \[\] should be non-empty"),
])
def test_a_bad_section_is_refused_naming_the_field(section, message):
    with pytest.raises(UserError, match=message):
        DemonstrationConfig.from_dict(section)


@pytest.mark.parametrize(("section", "message"), [
    ({**EXPERTS, "tasks": ["reach-v2"]}, r"unknown task 'reach-v2' in Meta-World suite metaworld_mt50"),
    ({**EXPERTS, "tasks": TASKS, "first_variation": 950}, r"first_variation 950 \+ max_attempts_per_task 100 reaches "
                                                           r"variation 1049; a task has variations 0..1008"),
])
def test_a_bad_task_or_variation_range_is_refused_before_any_worker(section, message, tmp_path):
    with pytest.raises(UserError, match=message):
        write_demonstrations(DemonstrationConfig.from_dict(section), tmp_path / "out", workers=2)
    assert not (tmp_path / "out").exists()


def test_the_schema_allows_exactly_the_dataclass_fields():
    import dataclasses

    from vlaquantbench.config import schema

    section = schema("config")["properties"]["demonstrations"]
    assert set(section["properties"]) == {f.name for f in dataclasses.fields(DemonstrationConfig)}
