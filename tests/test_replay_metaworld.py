"""Replay records any benchmark from its declared cameras (issue 50): the pi0.5 policy trained here on Meta-World
(`checkpoints/pi05_metaworld_cpu`) records one trajectory of a trained task, a full-precision replay reproduces its
chunks exactly (same observations, same noise), a quantized replay of the action head changes them with every
hook fired, and the layer diagnostics run on the recording as on LIBERO."""

from __future__ import annotations

import json

import numpy as np
import pytest

from paths import ROOT
from vlaquantbench.models.trained_home import policy_folder

pytestmark = pytest.mark.slow

HOME = ROOT / "checkpoints" / "pi05_metaworld_cpu"
TRAINING = json.loads((HOME / "training.json").read_text())
POLICY = policy_folder(HOME)
OBSERVE = ["paligemma_with_expert.gemma_expert.model.layers.*.mlp.down_proj"]
# The action head's linears, as the committed closed-loop cell of the same checkpoint quantized them.
HEAD_LAYERS = json.loads((ROOT / "results/methods_2026/metaworld/metaworld_mt50/pi05/rtn-W4A4-ah/header.json")
                         .read_text())["quant_report"]["ah"]["layers"]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    from vlaquantbench.replay.record import record
    from vlaquantbench.replay.study import RecordSettings

    folder = tmp_path_factory.mktemp("metaworld_replay")
    settings = RecordSettings(model="pi05", variant="full", suite="metaworld_mt50", benchmark="metaworld", tasks=[4],
                              init_states=[0], observe=OBSERVE, checkpoint=TRAINING["checkpoint"],
                              revision=TRAINING["revision"], checkpoint_dir=str(POLICY), max_steps=10,
                              executed_chunk=TRAINING["policy"]["n_action_steps"])
    trajectories = [folder / name for name in settings.trajectory_files()]
    meta = record(settings, folder / "records.json", trajectories)
    return folder, meta, trajectories


def _replay(recording, preset, layers=0):
    from vlaquantbench.replay.configuration import replay_configuration

    folder, _, trajectories = recording
    study = {"model": "pi05", "configurations": {"head": {"scope": "ah", "subset": None, "layers": layers}}}
    return replay_configuration(folder / "records.json", trajectories, study, "head", preset, str(POLICY))


def test_the_recording_holds_the_declared_camera_and_the_state(recording):
    folder, meta, trajectories = recording
    assert meta["benchmark"] == "metaworld" and meta["records"][0]["n_steps"] == 10
    with np.load(trajectories[0]) as data:
        assert {"image", "state"} <= set(data.files) and "agentview" not in data.files
        assert data["image"].ndim == 4 and len(data["image"]) == len(data["state"]) == meta["records"][0]["n_chunks"]


def test_a_full_precision_replay_reproduces_the_recording_and_a_quantized_one_does_not(recording):
    _, _, trajectories = recording
    with np.load(trajectories[0]) as data:
        recorded = data["chunk"]
    for _ in range(2):  # twice: the same observations and noise give the same chunks
        baseline = _replay(recording, "BASELINE")
        assert baseline.summary["records"][0]["dev_from_recorded_actions"] == 0.0
        np.testing.assert_array_equal(baseline.stacked("chunks"), recorded)
    quantized = _replay(recording, "W4A4", layers=HEAD_LAYERS)
    assert quantized.summary["hooks"]["selected"] == quantized.summary["hooks"]["fired"] == HEAD_LAYERS
    assert quantized.summary["records"][0]["dev_from_recorded_actions"] > 0


def test_layer_diagnostics_run_on_the_recording(recording, tmp_path):
    from vlaquantbench.diagnostics.collect import collect

    folder, _, trajectories = recording
    result = collect(folder / "records.json", trajectories, "pi05", "ah", "W4A4", tmp_path / "diag.json", str(POLICY))
    assert len(result["layers"]) == HEAD_LAYERS and result["provenance"]["tasks"] == [4]
    assert result["provenance"]["checkpoint_revision"] == TRAINING["revision"]
