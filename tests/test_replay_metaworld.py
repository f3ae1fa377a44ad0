"""Replay records any benchmark from its declared cameras, and the replay DAG records any study: a Meta-World replay
study (written here, named by `replay.study`) of the pi0.5 policy trained here on Meta-World
(`checkpoints/pi05_metaworld_cpu`) records one trajectory of a trained task through Snakemake, with the benchmark's
`main` camera at the size its cells render (the study's `runner.camera_size`) and the state. On that recording a full-precision replay reproduces its chunks exactly (same
observations, same noise), a quantized replay of the action head fires every hook it selects and changes them, and
the layer diagnostics run as on LIBERO. The replays and diagnostics run in this process: as Snakemake jobs each
would load torch and the policy anew (about 20 s a job here), and the replay rules run whole on LIBERO in
tests/test_replay_dag.py."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import yaml

from paths import ROOT
from vlaquantbench.models.trained_home import policy_folder

pytestmark = pytest.mark.slow

HOME = ROOT / "checkpoints" / "pi05_metaworld_cpu"
TRAINING = json.loads((HOME / "training.json").read_text())
POLICY = str(policy_folder(HOME))
# The committed closed-loop cell of the same checkpoint: the action head's linears it quantized, and the camera
# size its env rendered (the checkpoint's input size, which its training fixed: `models.trained_home`).
CELL = json.loads((ROOT / "results/methods_2026/metaworld/metaworld_mt50/pi05/rtn-W4A4-ah/header.json").read_text())
HEAD_LAYERS = CELL["quant_report"]["ah"]["layers"]
CELL_CAMERA_SIZE = CELL["config"]["runner"]["camera_size"]
NAME = "pi05_metaworld_cpu"
# The paper's replay study but for its policy, benchmark and trajectories: the same configurations (the trained
# policy has the released module names and depths).
PAPER = yaml.safe_load((ROOT / "config/replay/pi05_libero_spatial.yaml").read_text())
STUDY = {**PAPER, "checkpoint": TRAINING["checkpoint"], "revision": TRAINING["revision"], "benchmark": "metaworld",
         "suite": "metaworld_mt50", "tasks": [4], "init_states": [0], "formats": ["W4A4"], "all_formats_order": ["W4A4"],
         "bias_format": "W4A4", "runner": {"camera_size": CELL_CAMERA_SIZE}}


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """The recording the replay DAG's `replay_record` job writes for the study `replay.study` names."""
    work = tmp_path_factory.mktemp("replay_metaworld")
    for item in ("Snakefile", "rules", "workflow", "config", "src", "manifests"):
        (work / item).symlink_to(ROOT / item)
    (work.parent / f"{NAME}.yaml").write_text(yaml.safe_dump(STUDY))
    config = {"replay": {"study": str(work.parent / f"{NAME}.yaml"), "checkpoint_dir": POLICY, "max_steps": 10,
                         "executed_chunk": TRAINING["policy"]["n_action_steps"]}}
    (work.parent / "replay_metaworld.yaml").write_text(yaml.safe_dump(config))
    folder = work / "results" / "replay" / NAME / "records"
    run = subprocess.run([sys.executable, "-m", "snakemake", str(folder.relative_to(work) / "records.json"), "--cores", "1",
                          f"--configfile={work.parent / 'replay_metaworld.yaml'}"],
                         cwd=work, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-4000:]
    return folder, [folder / "t4_e0.npz"], work.parent / f"{NAME}.yaml"


def _replay(recording, preset, configuration):
    from vlaquantbench.replay.configuration import replay_configuration
    from vlaquantbench.replay.study import load_study

    folder, trajectories, study = recording
    study = load_study(study)
    return replay_configuration(folder / "records.json", trajectories, study, configuration, preset, POLICY)


def test_the_recording_holds_the_declared_camera_and_the_state(recording):
    """What the cells' policy observes: the declared camera at the cells' size (not Meta-World's default 480 px),
    the declared state; the probe keeps the declared action size of the policy's padded chunk."""
    from vlaquantbench.envs.metaworld.benchmark import CAMERA_SIZE
    from vlaquantbench.envs.registry import get_benchmark

    folder, [trajectory], _ = recording
    meta = json.loads((folder / "records.json").read_text())
    assert (meta["benchmark"], meta["revision"]) == ("metaworld", TRAINING["revision"])
    assert [(r["record"], r["n_steps"]) for r in meta["records"]] == [("t4_e0.npz", 10)]
    assert meta["env_settings"]["camera_size"] == CELL_CAMERA_SIZE != CAMERA_SIZE
    metaworld = get_benchmark("metaworld")
    with np.load(trajectory) as data:
        assert {"image", "state"} <= set(data.files) and "agentview" not in data.files
        calls = meta["records"][0]["n_chunks"]
        assert data["image"].shape == (calls, CELL_CAMERA_SIZE, CELL_CAMERA_SIZE, 3)
        assert data["state"].shape == (calls, metaworld.state_dim)
        # of the policy's chunk, padded to its max_action_dim, the probe keeps the declared action size
        assert data["chunk"].shape == (calls, TRAINING["policy"]["chunk_size"], metaworld.action_dim)
        assert data["actions"].shape == (10, metaworld.action_dim)


def test_a_full_precision_replay_reproduces_the_recording_and_a_quantized_one_does_not(recording):
    _, [trajectory], _ = recording
    with np.load(trajectory) as data:
        recorded = data["chunk"]
    for _ in range(2):  # twice: the same observations and noise give the same chunks
        baseline = _replay(recording, "BASELINE", "s167")
        assert baseline.summary["records"][0]["dev_from_recorded_actions"] == 0.0
        np.testing.assert_array_equal(baseline.stacked("chunks"), recorded)
    quantized = _replay(recording, "W4A4", "s167")
    assert quantized.summary["hooks"]["selected"] == quantized.summary["hooks"]["fired"] == HEAD_LAYERS
    assert quantized.summary["records"][0]["dev_from_recorded_actions"] > 0


def test_layer_diagnostics_run_on_the_recording(recording, tmp_path):
    from vlaquantbench.diagnostics.collect import collect

    folder, trajectories, _ = recording
    result = collect(folder / "records.json", trajectories, "pi05", "ah", "W4A4", tmp_path / "diag.json", POLICY)
    assert len(result["layers"]) == HEAD_LAYERS and result["provenance"]["tasks"] == [4]
    assert result["provenance"]["checkpoint_revision"] == TRAINING["revision"]
