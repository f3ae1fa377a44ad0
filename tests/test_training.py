"""Training the pi0.5 policy from scratch (`vlaquantbench.training`) on a tiny LeRobotDataset written
with lerobot's own writer, then loading the result through the rollout path's checkpoint loader."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from demonstrations_workflow import TINY_POLICY
from vlaquantbench.models.paligemma_family import REDUCED_WIDTHS_FILE

TASKS = ("Close a drawer", "Press a button from the top")
IMAGE = 28  # two 14-pixel patches a side: the 27-layer vision tower stays cheap on a CPU
STEPS = TINY_POLICY["decay_steps"]  # 40: trained to the end of the learning-rate decay


def write_tiny_dataset(root: Path, episodes_per_task: int = 2, frames: int = 6) -> Path:
    """A LeRobotDataset shaped like the Meta-World demonstrations: one camera, 4-D state and action."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.image": {"dtype": "image", "shape": (IMAGE, IMAGE, 3), "names": ["height", "width", "channel"]},
        "observation.state": {"dtype": "float32", "shape": (4,), "names": None},
        "action": {"dtype": "float32", "shape": (4,), "names": None},
    }
    dataset = LeRobotDataset.create("vlaquantbench/tiny-demos", fps=80, features=features, root=root, use_videos=False)
    rng = np.random.default_rng(0)
    for task, action in zip(TASKS, ([0.5, -0.5, 0.2, 1.0], [-0.3, 0.4, -0.6, -1.0])):
        for _ in range(episodes_per_task):
            for _ in range(frames):
                dataset.add_frame({
                    "observation.image": rng.integers(0, 256, (IMAGE, IMAGE, 3), dtype=np.uint8),
                    "observation.state": rng.uniform(-0.5, 0.5, 4).astype(np.float32),
                    # Each task's expert: one action, a little noise: something to learn.
                    "action": (np.array(action) + rng.normal(0, 0.05, 4)).astype(np.float32),
                    "task": task,
                })
            dataset.save_episode()
    dataset.finalize()
    return root


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from vlaquantbench.training import train_policy

    tmp = tmp_path_factory.mktemp("training")
    root = write_tiny_dataset(tmp / "dataset")
    manifest = tmp / "manifest.tsv"
    manifest.write_text("path\tsha256\n")
    record = train_policy(root, "vlaquantbench/tiny-demos", manifest, _config(tmp / "home"))
    return {"home": tmp / "home", "record": record, "provenance": tmp / "home" / "training.json"}


@pytest.mark.slow
def test_provenance_records_the_run(trained):
    record = json.loads(trained["provenance"].read_text())
    assert record == trained["record"]
    assert record["steps"] == record["planned_steps"] == STEPS and record["batch_size"] == 8 and record["seed"] == 0
    curve = record["loss_curve"]["mean_loss"]
    assert len(curve) == STEPS and all(np.isfinite(curve))
    # lerobot's flow-matching loss falls as the policy learns each task's action.
    assert np.mean(curve[-10:]) < 0.6 * np.mean(curve[:5])
    assert record["dataset"]["episodes"] == 4 and record["dataset"]["tasks"] == sorted(TASKS)
    assert len(record["dataset"]["manifest_sha256"]) == 64


@pytest.mark.slow
def test_checkpoint_is_a_plain_folder_at_its_weights_hash_with_every_file_recorded(trained):
    from vlaquantbench.hub.checks import sha256
    from vlaquantbench.training import weights_revision

    record, home = trained["record"], trained["home"]
    assert sorted(p.name for p in home.iterdir()) == ["policy", "tokenizer", "training.json"]
    snapshot = home / "policy"
    assert weights_revision(snapshot / "model.safetensors") == record["revision"]
    assert record["files"] == {p.relative_to(home).as_posix(): sha256(p) for p in sorted(home.rglob("*"))
                               if p.is_file() and p.name != "training.json"}
    assert {"policy/model.safetensors", "policy/config.json", "tokenizer/tokenizer.json"} <= set(record["files"])
    widths = json.loads((snapshot / REDUCED_WIDTHS_FILE).read_text())
    assert widths["vision"]["num_hidden_layers"] == 27 and widths["gemma_2b"]["depth"] == 18
    assert widths["gemma_300m"]["depth"] == 18 and widths["vocab_size"] % 64 == 0
    steps = json.loads((snapshot / "policy_preprocessor.json").read_text())["steps"]
    assert [s["config"]["tokenizer_name"] for s in steps if "tokenizer_name" in s.get("config", {})] == [
        "vlaquantbench/pi05-tiny-tokenizer"]


def _load(trained, device="cpu"):
    from vlaquantbench.models.adapter import AdapterConfig, make_adapter

    record = trained["record"]
    adapter = make_adapter(AdapterConfig(model="pi05", variant="full", checkpoint=record["checkpoint"],
                                         revision=record["revision"], checkpoint_dir=str(trained["home"] / "policy"),
                                         executed_chunk=2))
    adapter.load()
    return adapter


@pytest.mark.slow
def test_the_rollout_path_loads_it_as_a_released_checkpoint_and_acts_on_the_envs_observation(trained):
    import torch

    adapter = _load(trained)
    provenance = adapter.checkpoint_provenance
    assert provenance["tokenizer"]["repo"] == "vlaquantbench/pi05-tiny-tokenizer"
    assert provenance["tokenizer"]["revision"] == trained["record"]["tokenizer"]["revision"]
    assert provenance["widths"] == "reduced (trained here)" and provenance["training"]["steps"] == STEPS
    assert provenance["normalization"]["policy_preprocessor"]["norm_map"]["STATE"] == "MIN_MAX"
    # A Meta-World observation: one `image`, 4-D state, the task description.
    rng = np.random.default_rng(1)
    observations = [{"image": rng.integers(0, 256, (IMAGE, IMAGE, 3), dtype=np.uint8),
                     "state": rng.uniform(-0.5, 0.5, 4), "instruction": task} for task in TASKS]
    actions = adapter.act(observations, [adapter.reset(0), adapter.reset(1)])
    assert actions.shape == (2, 4, 4) and np.isfinite(actions).all()
    # The prompt is tokenized with no unknown word.
    tokens = adapter.preprocessor(adapter._lerobot_batch(observations))["observation.language.tokens"]
    unknown = adapter.preprocessor.steps[-2].input_tokenizer.unk_token_id
    assert not bool((tokens == unknown).any()) and tokens.dtype == torch.long


@pytest.mark.slow
def test_an_observation_without_the_checkpoints_camera_or_state_size_is_refused(trained):
    from vlaquantbench.errors import UserError

    adapter = _load(trained)
    wrist_only = {"wrist": np.zeros((IMAGE, IMAGE, 3), np.uint8), "state": np.zeros(4), "instruction": TASKS[0]}
    with pytest.raises(UserError, match=r"feed none of the checkpoint's cameras \['observation.image'\]"):
        adapter.act([wrist_only], [adapter.reset(0)])
    libero_state = {"image": np.zeros((IMAGE, IMAGE, 3), np.uint8), "state": np.zeros(8), "instruction": TASKS[0]}
    with pytest.raises(UserError, match="state has 8 dimensions; the checkpoint's observation.state has 4"):
        adapter.act([libero_state], [adapter.reset(0)])


@pytest.mark.slow
def test_the_rule_trains_on_the_demonstrations_rules_dataset(demonstrations_run):
    """`snakemake <output>/training.json`: rule demonstrations (two tasks, one episode each at 32 px: conftest.py's
    `demonstrations_run`, which tests/test_demonstrations.py reads too), then rule train_policy on its dataset, the
    provenance naming the dataset's manifest."""
    from demonstrations_workflow import TRAINING
    from vlaquantbench.envs.metaworld import lerobot_metaworld_config
    from vlaquantbench.hub.checks import sha256

    workdir = demonstrations_run["workdir"]
    record = json.loads((workdir / TRAINING["output"] / "training.json").read_text())
    assert record["dataset"]["manifest_sha256"] == sha256(demonstrations_run["out"] / "manifest.tsv")
    descriptions = lerobot_metaworld_config()["TASK_DESCRIPTIONS"]
    assert record["dataset"]["episodes"] == 2
    assert record["dataset"]["tasks"] == sorted(descriptions[task] for task in ("reach-v3", "handle-press-v3"))
    assert (workdir / TRAINING["output"] / "policy" / "model.safetensors").is_file() and (workdir / "logs" / "train_policy.log").is_file()


def _config(output, **changes):
    from vlaquantbench.training import TrainingConfig

    return TrainingConfig.from_dict({
        "model": "pi05", "output": str(output), "device": "cpu", "seed": 0, "steps": STEPS, "batch_size": 8,
        "log_every": 1, "checkpoint_repo": "vlaquantbench/pi05-tiny", "tokenizer_repo": "vlaquantbench/pi05-tiny-tokenizer",
        "policy": TINY_POLICY, **changes})


@pytest.mark.slow
def test_a_run_paused_at_its_time_limit_resumes_to_the_uninterrupted_runs_weights(trained, tmp_path):
    """The same command three times: the first two stop at `time_limit_s` with the state saved (the first with a
    limit shorter than loading the dataset, which the limit counts: it still takes one step), the third continues
    from it; the checkpoint is bit-equal to one run without a limit (the fixture's: same revision)."""
    from vlaquantbench.errors import UserError
    from vlaquantbench.training import TrainingPaused, train_policy

    root = write_tiny_dataset(tmp_path / "dataset")
    manifest = tmp_path / "manifest.tsv"
    manifest.write_text("path\tsha256\n")
    home = tmp_path / "home"
    provenance = home / "training.json"
    with pytest.raises(TrainingPaused, match=r"training.time_limit_s 1e-06: stopped after step 1 of 40"):
        train_policy(root, "vlaquantbench/tiny-demos", manifest, _config(home, time_limit_s=1e-6))
    with pytest.raises(TrainingPaused, match=r"training.time_limit_s 0.5: stopped after step (\d+) of 40") as paused:
        train_policy(root, "vlaquantbench/tiny-demos", manifest, _config(home, time_limit_s=0.5))
    state = home / "resume" / "state.pt"
    assert state.is_file() and not provenance.exists()
    assert 1 < int(str(paused.value).split("after step ")[1].split()[0]) < STEPS
    # Settings that change what is trained are refused by name; the saved state stays.
    with pytest.raises(UserError, match=r"saved by a run with other batch_size"):
        train_policy(root, "vlaquantbench/tiny-demos", manifest, _config(home, batch_size=4))
    assert state.is_file()
    record = train_policy(root, "vlaquantbench/tiny-demos", manifest, _config(home))
    assert record["revision"] == trained["record"]["revision"]
    assert record["loss_curve"] == trained["record"]["loss_curve"] and record["steps"] == STEPS
    assert not state.exists()


@pytest.mark.slow
def test_a_changed_or_unrecorded_file_in_the_checkpoint_folder_is_refused_at_load(trained, tmp_path):
    """A sign-flipped tensor is still a valid safetensors file, an edited config still a config: the load
    checks the folder against its training.json before lerobot reads anything, naming the file."""
    import shutil

    from safetensors.torch import load_file, save_file

    from vlaquantbench.errors import UserError

    record = trained["record"]
    named = rf"checkpoint vlaquantbench/pi05-tiny: vlaquantbench/pi05-tiny@{record['revision']}"

    def copy(name):
        home = tmp_path / name
        shutil.copytree(trained["home"], home)
        return home

    home = copy("flipped")
    weights = load_file(home / "policy" / "model.safetensors")
    first = sorted(weights)[0]
    weights[first] = -weights[first]
    save_file(weights, home / "policy" / "model.safetensors")
    with pytest.raises(UserError, match=rf"{named} .*policy/model.safetensors is not the weights of this revision"):
        _load({**trained, "home": home})
    home = copy("edited")
    config = home / "policy" / "config.json"
    config.write_text(config.read_text().replace('"chunk_size": 4', '"chunk_size": 3'))
    with pytest.raises(UserError, match=rf"{named} .*policy/config.json has SHA-256 [0-9a-f]{{64}}, but training.json records"):
        _load({**trained, "home": home})
    home = copy("unrecorded")
    (home / "tokenizer" / "added_tokens.json").write_text("{}")
    with pytest.raises(UserError, match=rf"{named} .*tokenizer/added_tokens.json is not recorded in training.json"):
        _load({**trained, "home": home})
    _load({**trained, "home": copy("untouched")})  # the same copy unchanged loads


@pytest.mark.slow
def test_device_frames_equal_lerobots_items_through_the_preprocessor(trained, tmp_path):
    """Every frame's tokens and normalized action chunk as lerobot's own path gives them:
    `LeRobotDataset` with the policy's delta timestamps (`__getitem__`), then the preprocessor."""
    import torch
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from vlaquantbench.models.pi05 import task_tokenizer, trained as trained_module
    from vlaquantbench.training.frames import DeviceFrames

    root = write_tiny_dataset(tmp_path / "dataset", frames=7)
    plain = LeRobotDataset("vlaquantbench/tiny-demos", root=root)
    tokenizer = task_tokenizer.build_task_tokenizer(sorted(TASKS))
    policy, preprocessor, _, _ = trained_module.build_policy(plain.meta, TINY_POLICY, "vlaquantbench/t", tokenizer, "cpu")
    frames = DeviceFrames(plain, preprocessor, policy.config.chunk_size, torch.device("cpu"))
    chunked = LeRobotDataset("vlaquantbench/tiny-demos", root=root,
                             delta_timestamps=resolve_delta_timestamps(policy.config, plain.meta))
    assert len(frames) == chunked.num_frames == 28
    for index in range(len(frames)):
        item = chunked[index]
        expected = preprocessor({k: v[None] if isinstance(v, torch.Tensor) else [v] for k, v in item.items()})
        got = frames.batch(torch.tensor([index]), shift_px=0)
        assert torch.equal(got["observation.language.tokens"], expected["observation.language.tokens"])
        assert torch.equal(got["observation.language.attention_mask"], expected["observation.language.attention_mask"])
        torch.testing.assert_close(got["action"], expected["action"])
        torch.testing.assert_close(got["observation.image"], expected["observation.image"], rtol=0, atol=0)


def test_random_shift_crops_each_image_of_the_replicate_padded_batch():
    import torch
    import torchvision.transforms.v2.functional as F

    from vlaquantbench.training.frames import random_shift

    generator = torch.Generator().manual_seed(3)
    images = torch.randint(0, 256, (16, 3, 12, 12), dtype=torch.uint8)
    shifted = random_shift(images, 2, torch.Generator().manual_seed(3))
    offsets = torch.randint(0, 5, (2, 16), generator=generator)
    padded = F.pad(images, [2, 2, 2, 2], padding_mode="edge")
    for i in range(16):
        assert torch.equal(shifted[i], F.crop(padded[i], int(offsets[0, i]), int(offsets[1, i]), 12, 12))
    assert not torch.equal(shifted, images)  # some sample moved


def test_the_study_configs_training_target_plans_demonstrations_and_training_on_a_clean_checkout(tmp_path):
    """`snakemake -n checkpoints/pi05_metaworld/training.json --configfile config/trained_study.yaml`, the command
    benchmarks/gpu_train_policy.sh runs, in a checkout without the checkpoint: the DAG holds the two jobs."""
    import re
    import subprocess
    import sys

    from paths import ROOT

    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "config", "src"):
        (checkout / item).symlink_to(ROOT / item)
    run = subprocess.run([sys.executable, "-m", "snakemake", "-n", "checkpoints/pi05_metaworld/training.json",
                          "--configfile", "config/trained_study.yaml"], cwd=checkout, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    jobs = {job: int(count) for job, count in re.findall(r"^(\w+) +(\d+)$", run.stdout, re.MULTILINE)}
    assert jobs == {"demonstrations": 1, "train_policy": 1, "total": 2}, run.stdout[-2000:]


@pytest.mark.slow
def test_a_paused_run_ended_where_its_state_stands_is_a_checkpoint_of_the_saved_weights(tmp_path):
    """`checkpoint_from_saved_state`: the checkpoint holds the weights the paused run saved, its provenance
    says where it stopped, why and after how many of the planned steps, and the rollout path loads it."""
    import torch
    from safetensors.torch import load_file

    from vlaquantbench.errors import UserError
    from vlaquantbench.training import TrainingPaused, checkpoint_from_saved_state, train_policy

    root = write_tiny_dataset(tmp_path / "dataset")
    manifest = tmp_path / "manifest.tsv"
    manifest.write_text("path\tsha256\n")
    home = tmp_path / "home"
    with pytest.raises(TrainingPaused):
        train_policy(root, "vlaquantbench/tiny-demos", manifest, _config(home, time_limit_s=0.5))
    saved = torch.load(home / "resume" / "state.pt", weights_only=False)
    with pytest.raises(UserError, match=r"saved by a run with other seed than this training section"):
        checkpoint_from_saved_state(root, "vlaquantbench/tiny-demos", manifest, _config(home, seed=1), "a test")
    record = checkpoint_from_saved_state(root, "vlaquantbench/tiny-demos", manifest, _config(home),
                                         "the test stops it here", {"type": "cpu"})
    assert record["stopped_early"]["at_step"] == saved["step"] == record["steps"] < STEPS
    assert record["stopped_early"]["why"] == "the test stops it here" and record["planned_steps"] == STEPS
    assert not (home / "resume" / "state.pt").exists()
    adapter = _load({"home": home, "record": record})
    assert adapter.checkpoint_provenance["training"]["stopped_early"]["at_step"] == saved["step"]
    weights = load_file(home / "policy" / "model.safetensors")
    assert weights and set(weights) <= set(saved["policy"])  # save_pretrained drops tied copies only
    for name, value in weights.items():
        assert torch.equal(value, saved["policy"][name]), name


@pytest.mark.parametrize("settings, refusal", [
    ({"cuda_graph": True}, r"training.cuda_graph: true needs a CUDA device; training.device is 'cpu'"),
    ({"cuda_graph": True, "compile_mode": "default", "device": "cuda"},
     r"training.cuda_graph and training.compile_mode each speed the step up: set one of them"),
])
def test_a_captured_step_is_refused_where_it_cannot_run_before_the_dataset_loads(tmp_path, settings, refusal):
    from vlaquantbench.errors import UserError
    from vlaquantbench.training import train_policy

    (tmp_path / "dataset" / "meta").mkdir(parents=True)
    (tmp_path / "dataset" / "meta" / "info.json").write_text("{}")  # the refusal comes before it is read
    with pytest.raises(UserError, match=refusal):
        train_policy(tmp_path / "dataset", "vlaquantbench/tiny-demos", tmp_path / "manifest.tsv",
                     _config(tmp_path / "home", **settings))
