"""The cell config is typed to the end (issue 50): its stopping rule (`SequentialSpec`), its client's conventions
(`ClientConventions`) and the values that differ from them (`CellOverrides`), the checkpoint stamp a job loads from (`CheckpointStamp`) and a config's `training` section
(`TrainingConfig`) are dataclasses, each checked by the schema rules of the YAML values it stands for, and the typed
forms keep every cell's canonical form and hash, and what training.json records."""

from __future__ import annotations

import dataclasses
import json

import pytest

from demo_study import demo_study
from paths import ROOT
from vlaquantbench.cells import AgainstCell, CellConfig, CellOverrides, Override, SequentialSpec, cell_config, config_hash
from vlaquantbench.config.study import StudyConfig
from vlaquantbench.errors import UserError
from vlaquantbench.models.client import ClientConventions, client_conventions
from vlaquantbench.runner.checkpoint import CheckpointStamp, download_checkpoint
from vlaquantbench.training import TrainingConfig

SPATIAL_PI05 = "libero/libero_spatial/pi05"


def test_a_sequential_cell_reads_back_typed_with_its_hash():
    study = StudyConfig.from_dict(demo_study("pi05", sequential={"against": "rtn-BASELINE-e2e", "alpha": 0.1}))
    cell = CellConfig.from_ref(f"{SPATIAL_PI05}/rtn-W4A4-e2e", study)
    against = CellConfig.from_ref(f"{SPATIAL_PI05}/rtn-BASELINE-e2e", study)
    assert cell.sequential == SequentialSpec(0.1, 5.0, AgainstCell(against.ref, against.config_hash))
    assert against.sequential is None and "sequential" not in against.to_dict()
    assert isinstance(cell.client, ClientConventions) and cell.client == client_conventions("pi05")
    again = CellConfig.from_dict(cell.to_dict())
    assert again == cell and again.config_hash == cell.config_hash
    assert cell.to_dict()["sequential"] == {"alpha": 0.1, "margin_pp": 5.0,
                                            "against": {"ref": against.ref, "config_hash": against.config_hash}}


def test_a_sequential_spec_outside_the_schema_is_refused_naming_the_field():
    against = AgainstCell(f"{SPATIAL_PI05}/rtn-BASELINE-e2e", "0123456789ab")
    with pytest.raises(UserError, match=r"against 'libero/libero_spatial/pi05/rtn-BASELINE-e2e': study\.sequential\.alpha"):
        SequentialSpec(1.5, 5.0, against)
    with pytest.raises(UserError, match=r"study\.sequential\.margin_pp"):
        SequentialSpec.from_dict({"alpha": 0.05, "margin_pp": 0, "against": dataclasses.asdict(against)})


def test_client_conventions_outside_the_schema_are_refused_naming_the_field():
    released = client_conventions("pi05")
    with pytest.raises(UserError, match=r"client conventions \(.*\): study\.runner\.control_mode"):
        dataclasses.replace(released, control_mode="relative")
    with pytest.raises(UserError, match=r"study\.runner\.executed_chunk"):
        dataclasses.replace(released, executed_chunk=0)
    with pytest.raises(UserError, match="episodes_per_task"):
        ClientConventions(**{**released.as_dict(), "episodes_per_task": 0})


def test_a_cells_overrides_are_typed_and_keep_their_canonical_form_and_hash():
    study = StudyConfig.from_dict({"models": {"pi05": {"variant": "demo", "runner": {"executed_chunk": 5,
                                                                                    "control_mode": "absolute"}}},
                                   "tasks": 1, "episodes_per_task": 2})
    cell = CellConfig.from_ref(f"{SPATIAL_PI05}/rtn-W4A4-ah", study)
    assert cell.overrides == CellOverrides(executed_chunk=Override(10, 5), control_mode=Override("delta", "absolute"),
                                           episodes_per_task=Override(20, 2))
    canonical = cell.to_dict()
    # the canonical form is the dict of the values that differ, as before the overrides were typed
    assert canonical["overrides"] == {"executed_chunk": {"client": 10, "cell": 5}, "episodes_per_task": {"client": 20, "cell": 2},
                                      "control_mode": {"client": "delta", "cell": "absolute"}}
    again = CellConfig.from_dict(canonical)
    assert again == cell and config_hash(again.to_dict()) == cell.config_hash
    with pytest.raises(UserError, match=r"^cell x: overrides: camera_size is not a value a client sets \(executed_chunk, "
                                        r"control_mode, mujoco, episodes_per_task, max_steps\)"):
        CellOverrides.from_dict({"camera_size": {"client": 256, "cell": 128}}, "cell x")
    with pytest.raises(UserError, match=r"^cell overrides: executed_chunk\.cell: .*executed_chunk: 0 is less than the minimum of 1"):
        CellOverrides(executed_chunk=Override(10, 0))
    with pytest.raises(UserError, match=r"^cell overrides: max_steps: Override\(client=500, cell=500\) is not a value that differs"):
        CellOverrides(max_steps=Override(500, 500))


def test_a_stamp_is_read_once_typed_and_a_malformed_one_is_refused_naming_file_and_field(tmp_path):
    stamp = tmp_path / "checkpoint.json"
    download_checkpoint("pi05", "demo", "lerobot/pi05_libero_finetuned_v044", None, stamp)
    assert CheckpointStamp.read(stamp) == CheckpointStamp("pi05", "demo", "lerobot/pi05_libero_finetuned_v044", None, None)
    written = json.loads(stamp.read_text())
    stamp.write_text(json.dumps({**written, "hf_hom": "/tmp/x"}))
    with pytest.raises(UserError, match=rf"{stamp}: .*hf_hom"):
        CheckpointStamp.read(stamp)
    stamp.write_text(json.dumps({**written, "path": 3}))
    with pytest.raises(UserError, match=rf"{stamp}: path: 3 is not of type"):
        CheckpointStamp.read(stamp)
    stamp.write_text("{")
    with pytest.raises(UserError, match=str(stamp)):
        CheckpointStamp.read(stamp)


def test_client_conventions_are_keyed_by_model_and_benchmark(monkeypatch):
    """A model's client.py may declare its conventions per benchmark (`BENCHMARK_CLIENTS`); a cell on that benchmark
    takes them, a cell elsewhere the model's `CLIENT`; a key naming no registered benchmark is refused."""
    import importlib

    module = importlib.import_module("vlaquantbench.models.metaworld_expert.client")
    study = {"models": {"metaworld_expert": {"variant": "full"}}, "tasks": 1}
    ref = "metaworld/metaworld_easy/metaworld_expert/rtn-BASELINE-e2e"
    assert cell_config(ref, study)["episodes_per_task"] == module.CLIENT.episodes_per_task == 50
    on_metaworld = dataclasses.replace(module.CLIENT, episodes_per_task=7, source="a Meta-World client")
    monkeypatch.setattr(module, "BENCHMARK_CLIENTS", {"metaworld": on_metaworld}, raising=False)
    cfg = cell_config(ref, study)
    assert cfg["episodes_per_task"] == 7 and cfg["client"] == on_metaworld.as_dict() and cfg["overrides"] == {}
    assert client_conventions("metaworld_expert") == module.CLIENT  # no benchmark: the model's CLIENT
    assert client_conventions("metaworld_expert", "libero") == module.CLIENT
    monkeypatch.setattr(module, "BENCHMARK_CLIENTS", {"robocasa": on_metaworld})
    with pytest.raises(UserError, match=r"model 'metaworld_expert': BENCHMARK_CLIENTS of its client.py names robocasa; "
                                        r"registered benchmarks: libero, metaworld"):
        client_conventions("metaworld_expert", "metaworld")


def test_the_training_section_is_typed_with_its_defaults_and_keeps_what_training_json_records():
    """config/trained_cpu.yaml's section, typed: the defaults its training ran with, and the policy settings in the
    key order the committed checkpoint's training.json records them (written verbatim, so the same section
    writes the same file)."""
    from vlaquantbench.config import load_yaml

    raw = load_yaml(ROOT / "config" / "trained_cpu.yaml", "config")["training"]
    training = TrainingConfig.from_dict(raw, "config/trained_cpu.yaml")
    assert (training.steps, training.batch_size, training.time_limit_s) == (1500, 16, 660)
    assert (training.precision, training.random_shift_px, training.compile_mode, training.cuda_graph) == ("float32", 0, None, False)
    recorded = json.loads((ROOT / training.output / "training.json").read_text())
    assert json.dumps(recorded["policy"]) == json.dumps(training.policy)
    assert (recorded["checkpoint"], recorded["planned_steps"], recorded["seed"]) == (training.checkpoint_repo, 1500, 0)
    assert TrainingConfig.from_dict(training.as_dict()) == training


@pytest.mark.parametrize("change, refusal", [
    ({"step": 10}, r"config/x.yaml: training: unknown key 'step'; allowed keys: batch_size, "),
    ({"steps": "many"}, r"config/x.yaml: training.steps: 'many' is not of type 'integer'"),
    ({"cuda_graph": "yes"}, r"config/x.yaml: training.cuda_graph: 'yes' is not of type 'boolean'"),
    ({"precision": "float16"}, r"config/x.yaml: training.precision: 'float16' is not allowed; allowed values: float32, bfloat16"),
])
def test_an_unknown_or_ill_typed_training_field_is_refused_naming_it(change, refusal):
    raw = load_training()
    with pytest.raises(UserError, match=refusal):
        TrainingConfig.from_dict({**raw, **change}, "config/x.yaml")


def test_a_training_section_built_in_code_is_held_to_the_same_rules():
    training = TrainingConfig.from_dict(load_training())
    with pytest.raises(UserError, match=r"training section \(output 'checkpoints/pi05_metaworld_cpu'\): "
                                        r"training\.batch_size: 0 is less than the minimum of 1"):
        dataclasses.replace(training, batch_size=0)
    with pytest.raises(UserError, match=r"training\.policy\.lr: 0 is less than or equal to the minimum of 0"):
        dataclasses.replace(training, policy={**training.policy, "lr": 0})


def load_training() -> dict:
    import yaml

    return yaml.safe_load((ROOT / "config" / "trained_cpu.yaml").read_text())["training"]
