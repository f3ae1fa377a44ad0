"""Step limits are each model's (`models/<model>/client.py` STEP_LIMITS) or a benchmark's own (Meta-World's 500),
resolved into the hashed cell config when the DAG is built: a model's limit changing reruns its cells, and a
model whose client never ran on a benchmark is refused by name before any job starts."""

import pytest
from demo_study import demo_study

from vlaquantbench.cells import cell_config, config_hash
from vlaquantbench.errors import UserError


def study_without_max_steps(*models: str) -> dict:
    study = demo_study(*models)
    del study["runner"]["max_steps"]
    return study


@pytest.mark.parametrize(("model", "suite", "limit"), [
    ("pi05", "libero_goal", 300), ("pi0", "libero_10", 520), ("openvla_oft", "libero_spatial", 220),
    ("xvla", "libero_10", 900),
])
def test_a_cell_runs_under_its_models_limit_on_its_suite_recorded_in_its_config(model, suite, limit):
    cfg = cell_config(f"libero/{suite}/{model}/rtn-BASELINE-e2e", study_without_max_steps(model))
    assert cfg["runner"]["max_steps"] == limit and "max_steps" not in cfg["overrides"]


def test_a_study_limit_is_an_override_of_the_models_and_changes_the_hash():
    ref = "libero/libero_goal/pi05/rtn-BASELINE-e2e"
    released = cell_config(ref, study_without_max_steps("pi05"))
    shortened = cell_config(ref, demo_study("pi05", max_steps=30))
    assert shortened["overrides"]["max_steps"] == {"client": 300, "cell": 30}
    assert config_hash(shortened) != config_hash(released)


def test_meta_world_cells_take_meta_worlds_own_limit():
    cfg = cell_config("metaworld/metaworld_mt10/metaworld_expert/rtn-BASELINE-e2e",
                      {"models": {"metaworld_expert": {"variant": "full"}}, "tasks": 1, "episodes_per_task": 1})
    assert cfg["runner"]["max_steps"] == 500


def test_a_model_without_a_limit_on_the_benchmark_is_refused_naming_it():
    study = {"models": {"metaworld_expert": {"variant": "full"}}, "tasks": 1, "episodes_per_task": 1}
    with pytest.raises(UserError, match="cell 'libero/libero_spatial/metaworld_expert/rtn-BASELINE-e2e': model "
                                        "'metaworld_expert' has no step limit on libero suite 'libero_spatial'"):
        cell_config("libero/libero_spatial/metaworld_expert/rtn-BASELINE-e2e", study)
