"""Meta-World through the project's batched worker env, on the real simulator (CPU): the scripted
experts (the `metaworld_expert` model entry) driven by the closed-loop runner's `run_episodes` succeed,
episodes do not depend on the batch they ran in, seeded variations are reproducible, bad suites and
tasks are refused by name, and the `corner2` image has lerobot's orientation."""

from __future__ import annotations

import os

import numpy as np
import pytest

from vlaquantbench.envs import make_env, make_suite
from vlaquantbench.envs.metaworld import STEP_LIMIT, MetaWorldSuite
from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.runner.loop import run_episodes

pytestmark = pytest.mark.slow

# The tasks the experts were checked on when Meta-World was added, all in MT10.
TASKS = ("reach-v3", "button-press-topdown-v3", "drawer-close-v3", "door-open-v3", "pick-place-v3")
EPISODES_PER_TASK = 5


@pytest.fixture(scope="module")
def suite() -> MetaWorldSuite:
    return make_suite("metaworld", "metaworld_mt10")


@pytest.fixture(scope="module")
def expert():
    adapter = make_adapter(AdapterConfig(model="metaworld_expert", variant="full"))
    adapter.load()
    return adapter


def run_experts(suite, expert, num_envs: int) -> dict:
    specs = suite.episodes(EPISODES_PER_TASK, task_ids=[suite.task_id(t) for t in TASKS])
    records = []
    # The experts read no image: the workers render none.
    with make_env("metaworld", suite, num_envs, camera_size=None if not expert.reads_images else 480) as env:
        run_episodes(expert, env, specs, suite.step_limit, records.extend)
    return {(r["task_id"], r["episode"]): r for r in records}


@pytest.fixture(scope="module")
def one_worker(suite, expert) -> dict:
    return run_experts(suite, expert, num_envs=1)


def test_experts_succeed_through_the_batched_env(suite, one_worker):
    """If the wrapper scaled actions, sliced the state, seeded variations or read success wrongly, the
    experts would fail (measured with metaworld 3.0.0: 24/25 of these episodes succeed)."""
    assert len(one_worker) == len(TASKS) * EPISODES_PER_TASK
    for task in TASKS:
        outcomes = [r for r in one_worker.values() if r["task_name"] == task]
        rate = sum(r["success"] for r in outcomes) / len(outcomes)
        assert rate >= 0.8, (task, [(r["episode"], r["success"], r["steps"]) for r in outcomes])
        assert all(0 < r["steps"] <= STEP_LIMIT for r in outcomes)
        assert all(r["steps"] < STEP_LIMIT for r in outcomes if r["success"])
    # Episodes of a task start from different variations, each recorded: the experts take different paths.
    assert len({r["actions_sha256"] for r in one_worker.values()}) == len(one_worker)
    assert len({tuple(r["task_variation"]) for r in one_worker.values()}) == len(one_worker)


def test_episodes_do_not_depend_on_the_batch_they_ran_in(suite, expert, one_worker):
    four_workers = run_experts(suite, expert, num_envs=4)
    assert four_workers.keys() == one_worker.keys()
    for key, record in one_worker.items():
        same = ("success", "steps", "actions_sha256", "seed", "init_state_id", "task_variation")
        assert {k: four_workers[key][k] for k in same} == {k: record[k] for k in same}, key


def test_variations_are_seeded_and_reproducible_in_any_slot(suite):
    task_id = suite.task_id("pick-place-v3")
    first, second = suite.episode_spec(task_id, 0), suite.episode_spec(task_id, 1)
    with make_env("metaworld", suite, 2, camera_size=None) as env:
        a = env.reset([first, second])
        b = env.reset([second, first])
    assert "image" not in a[0]  # nothing rendered when no image is asked for
    np.testing.assert_array_equal(a[0]["task_variation"], b[1]["task_variation"])
    np.testing.assert_array_equal(a[0]["environment_state"], b[1]["environment_state"])
    assert not np.array_equal(a[0]["task_variation"], a[1]["task_variation"])
    assert a[0]["state"].shape == (4,) and a[0]["instruction"] == suite.task(task_id).instruction


@pytest.mark.parametrize("benchmark, suite_name, message", [
    ("metaworld", "metaworld_impossible", r"unknown Meta-World suite 'metaworld_impossible'; expected one of "
                                          r"metaworld_easy, .*metaworld_mt50"),
    ("meta-world", "metaworld_easy", r"unknown benchmark 'meta-world'; known: libero, metaworld"),
])
def test_unknown_benchmark_or_suite_is_refused_by_name(benchmark, suite_name, message):
    with pytest.raises(UserError, match=message):
        make_env(benchmark, suite_name, 1, camera_size=None)


def test_unknown_env_setting_is_refused_by_name():
    with pytest.raises(UserError, match=r"unknown metaworld env setting\(s\) settle_steps; known: camera_size, "
                                        r"mujoco, reply_timeout_s"):
        make_env("metaworld", "metaworld_easy", 1, settle_steps=10)


def test_unknown_task_is_refused_by_name(suite):
    with pytest.raises(UserError, match=r"unknown task 'pick-place-v2' in Meta-World suite metaworld_mt10; "
                                        r"its tasks: reach-v3, push-v3"):
        suite.task_id("pick-place-v2")
    with pytest.raises(UserError, match=r"task_id 10 is out of range for metaworld_mt10 \(0..9\)"):
        suite.episode_spec(10, 0)


def test_step_limit_is_metaworlds_path_length():
    from metaworld.sawyer_xyz_env import SawyerXYZEnv

    assert STEP_LIMIT == SawyerXYZEnv.max_path_length


def test_corner2_image_has_lerobots_orientation(suite):
    """The same variation seen by lerobot 0.6.1's own `MetaworldEnv` (480 px, in this process) and by a
    worker: at lerobot's size the images, `agent_pos` and Meta-World's whole observation are equal; at 224 px the image is lerobot's
    shrunk (mean error 1.3 of 255; its mirror images' 42-56), so the flips hold at the size policies read."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    from PIL import Image
    from lerobot.envs.metaworld import MetaworldEnv

    task_id = suite.task_id("drawer-close-v3")
    spec = suite.episode_spec(task_id, 3)
    seed = suite.variation_seed(task_id, spec.init_state_id)
    reference = MetaworldEnv(task=suite.task(task_id).name, obs_type="pixels_agent_pos")
    try:
        observation, _ = reference.reset(seed=seed)
        # Meta-World's whole observation after the reset (the frame stack holds the reset's frame twice).
        environment_state = reference._env._get_obs()
    finally:
        reference.close()
    with make_env("metaworld", suite, 1, camera_size=480) as env:
        [ours] = env.reset([spec])
    np.testing.assert_array_equal(ours["state"], observation["agent_pos"])
    np.testing.assert_array_equal(ours["environment_state"], environment_state)
    np.testing.assert_array_equal(ours["image"], observation["pixels"])
    with make_env("metaworld", suite, 1, camera_size=224) as env:
        [small] = env.reset([spec])
    assert small["image"].shape == (224, 224, 3)
    shrunk = np.asarray(Image.fromarray(observation["pixels"]).resize((224, 224), Image.BILINEAR), dtype=float)

    def error(image):
        return np.abs(image.astype(float) - shrunk).mean()

    upright = error(small["image"])
    for mirrored in (small["image"][::-1], small["image"][:, ::-1], small["image"][::-1, ::-1]):
        assert error(mirrored) > 10 * upright, (error(mirrored), upright)
