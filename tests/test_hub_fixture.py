"""The released checkpoints' loading path, offline, on the hub fixture (`vqb hub-fixture`):
huggingface_hub and lerobot resolve it like the real repositories; each fault a snapshot can carry
is refused before any rollout, naming the file or revision; actions are unnormalized with the
checkpoint's own statistics and prompts tokenized with its own tokenizer."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from vlaquantbench.errors import UserError
from vlaquantbench.hub.cache import offline_cache
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.models.client import adapter_conventions
from vlaquantbench.runner.checkpoint import download_checkpoint

PI05 = "lerobot/pi05_libero_finetuned_v044"
TOKENIZER = "google/paligemma-3b-pt-224"


def pinned(hub_fixture, model="pi05"):
    entry = hub_fixture["study"]["models"][model]
    return entry["checkpoint"], entry["revision"]


def load(hub_fixture, folder, model="pi05", revision=None, home=None):
    checkpoint, pinned_revision = pinned(hub_fixture, model)
    adapter = make_adapter(AdapterConfig(model=model, variant="full", checkpoint=checkpoint,
                                         revision=revision or pinned_revision, checkpoint_dir=str(folder)))
    with offline_cache(home or hub_fixture["home"]):
        adapter.load()
    return adapter


def snapshot_copy(hub_fixture, tmp_path, repo=PI05) -> Path:
    """A writable copy of a checkpoint snapshot, in a folder named by its revision like the cache's."""
    source = Path(hub_fixture["repos"][repo]["path"])
    return Path(shutil.copytree(source, tmp_path / "snapshots" / source.name))


def test_the_fixture_resolves_through_huggingface_hub_and_transformers_offline(hub_fixture):
    from huggingface_hub import snapshot_download
    from transformers import AutoTokenizer

    checkpoint, revision = pinned(hub_fixture)
    with offline_cache(hub_fixture["home"]):
        folder = Path(snapshot_download(checkpoint, revision=revision, local_files_only=True))
        tokenizer = AutoTokenizer.from_pretrained(TOKENIZER)
    assert folder.name == revision and folder.parent.parent.name == "models--lerobot--pi05_libero_finetuned_v044"
    assert {p.name for p in folder.iterdir()} == {
        "config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json",
        "policy_preprocessor_step_3_normalizer_processor.safetensors",
        "policy_postprocessor_step_0_unnormalizer_processor.safetensors", "vlaquantbench_reduced_widths.json",
    }
    assert all(p.is_symlink() and p.resolve().parent.name == "blobs" for p in folder.iterdir())
    assert (folder.parent.parent / "refs" / "main").read_text() == revision
    assert json.loads((folder / "config.json").read_text())["type"] == "pi05"
    assert type(tokenizer).__name__ == "GemmaTokenizer"
    ids = tokenizer("Task: pick up the black bowl, State: 3 255;\nAction: ").input_ids
    assert ids[0] == tokenizer.bos_token_id == 2 and tokenizer.convert_ids_to_tokens(0) == "<pad>"
    assert tokenizer.decode(ids[1:]) == "Task: pick up the black bowl, State: 3 255;\nAction: "


def test_a_snapshot_of_another_revision_is_refused_naming_both(hub_fixture, tmp_path):
    checkpoint, revision = pinned(hub_fixture)
    other = "1" * 40
    with offline_cache(hub_fixture["home"]), pytest.raises(UserError, match=rf"{checkpoint}@{other}.*holds revisions {revision}"):
        download_checkpoint("pi05", "full", checkpoint, other, tmp_path / "checkpoint.json")
    folder = hub_fixture["repos"][checkpoint]["path"]
    with pytest.raises(UserError, match=rf"snapshot {folder} is revision {revision}, but the config pins revision {other}"):
        load(hub_fixture, folder, revision=other)


@pytest.mark.parametrize("fault, message", [
    ("missing_postprocessor", r"processor file policy_postprocessor.json is missing"),
    ("corrupt_preprocessor", r"processor file .*policy_preprocessor.json is corrupt"),
    ("missing_normalizer", r"normalizer state file policy_preprocessor_step_3_normalizer_processor.safetensors .* missing"),
    ("corrupt_unnormalizer", r"normalizer state file .*policy_postprocessor_step_0_unnormalizer_processor.safetensors is corrupt"),
    ("statistics_without_std", r"unnormalizer_processor.safetensors lacks action.std, which MEAN_STD normalization"),
])
def test_a_missing_or_corrupt_processor_file_is_refused_naming_it(hub_fixture, tmp_path, fault, message):
    folder = snapshot_copy(hub_fixture, tmp_path)
    unnormalizer = folder / "policy_postprocessor_step_0_unnormalizer_processor.safetensors"
    if fault == "missing_postprocessor":
        (folder / "policy_postprocessor.json").unlink()
    elif fault == "corrupt_preprocessor":
        (folder / "policy_preprocessor.json").write_text('{"name": "policy_preprocessor", "steps": [')
    elif fault == "missing_normalizer":
        (folder / "policy_preprocessor_step_3_normalizer_processor.safetensors").unlink()
    elif fault == "corrupt_unnormalizer":
        unnormalizer.write_bytes(unnormalizer.read_bytes()[:100])
    else:
        stats = {k: v for k, v in load_file(unnormalizer).items() if k != "action.std"}
        unnormalizer.unlink()
        save_file(stats, unnormalizer)
    with pytest.raises(UserError, match=message):
        load(hub_fixture, folder)


@pytest.mark.parametrize("fault, message", [
    ("missing", r"does not fit the architecture: 1 missing keys: model.action_out_proj.bias"),
    ("unexpected", r"does not fit the architecture: 1 unexpected keys: model.extra_head.weight"),
    ("shape", r"does not fit the architecture: wrong shapes: model.action_in_proj.weight \(32, 16\) vs \(32, 32\)"),
])
def test_a_state_dict_that_does_not_fit_the_architecture_is_refused(hub_fixture, tmp_path, fault, message):
    folder = snapshot_copy(hub_fixture, tmp_path)
    weights = folder / "model.safetensors"
    state = load_file(weights)
    if fault == "missing":
        del state["model.action_out_proj.bias"]
    elif fault == "unexpected":
        state["model.extra_head.weight"] = torch.zeros(2, 2)
    else:
        state["model.action_in_proj.weight"] = state["model.action_in_proj.weight"][:, :16].contiguous()
    weights.unlink()
    save_file(state, weights)
    with pytest.raises(UserError, match=rf"state dict {weights} {message}"):
        load(hub_fixture, folder)


def test_a_tokenizer_that_does_not_load_is_refused_naming_it(hub_fixture, tmp_path):
    # A cache whose PaliGemma tokenizer.json is truncated; the checkpoints are the fixture's.
    home = tmp_path / "hf"
    (home / "hub").mkdir(parents=True)
    for repo in Path(hub_fixture["home"], "hub").iterdir():
        if repo.name == "models--google--paligemma-3b-pt-224":
            shutil.copytree(repo, home / "hub" / repo.name, symlinks=True)
        else:
            (home / "hub" / repo.name).symlink_to(repo)
    blob = next((home / "hub" / "models--google--paligemma-3b-pt-224" / "snapshots").glob("*/tokenizer.json")).resolve()
    blob.write_text(blob.read_text()[:500])
    with pytest.raises(UserError, match=rf"tokenizer {TOKENIZER} \(named by policy_preprocessor.json\) does not load"):
        load(hub_fixture, hub_fixture["repos"][PI05]["path"], home=home)


def test_actions_are_unnormalized_with_the_checkpoints_statistics_and_prompts_use_its_tokenizer(hub_fixture):
    from transformers import AutoTokenizer

    folder = Path(hub_fixture["repos"][PI05]["path"])
    adapter = load(hub_fixture, folder)
    # By hand, from the files: the postprocessor's unnormalizer step, its mode and its statistics.
    step = next(s for s in json.loads((folder / "policy_postprocessor.json").read_text())["steps"]
                if s["registry_name"] == "unnormalizer_processor")
    assert step["config"]["norm_map"]["ACTION"] == "MEAN_STD"
    stats = load_file(folder / step["state_file"])
    normalized = torch.randn(3, 50, 7, generator=torch.Generator().manual_seed(0))
    expected = normalized.double().numpy() * stats["action.std"].double().numpy() + stats["action.mean"].double().numpy()
    np.testing.assert_allclose(adapter.postprocessor(normalized.clone()).numpy(), expected, rtol=0, atol=1e-6)

    header = adapter.checkpoint_provenance
    assert header["normalization"]["policy_postprocessor"]["state_files"] == {step["state_file"]: adapter_sha(folder / step["state_file"])}
    assert header["tokenizer"]["class"] == "GemmaTokenizer" and header["tokenizer"]["repo"] == TOKENIZER
    assert header["tokenizer"]["revision"] == hub_fixture["repos"][TOKENIZER]["revision"]
    assert header["widths"] == "reduced (offline hub fixture)"
    # pi0.5's prompt carries the state, normalized with the checkpoint's statistics, in 256 bins.
    state = stats["observation.state.mean"].numpy()  # normalizes to 0.0, the lower edge of bin 128 of 256 on [-1, 1]
    batch = adapter.preprocessor({
        "observation.images.image": torch.zeros(1, 3, 128, 128), "observation.images.image2": torch.zeros(1, 3, 128, 128),
        "observation.state": torch.from_numpy(state[None]), "task": ["put the bowl on the plate"],
    })
    with offline_cache(hub_fixture["home"]):
        tokenizer = AutoTokenizer.from_pretrained(TOKENIZER)
    prompt = "Task: put the bowl on the plate, State: " + " ".join(["128"] * 8) + ";\nAction: "
    ids = tokenizer(prompt).input_ids
    tokens = batch["observation.language.tokens"][0]
    assert tokens[: len(ids)].tolist() == ids and not batch["observation.language.attention_mask"][0, len(ids):].any()


def adapter_sha(path):
    from vlaquantbench.hub.checks import sha256

    return sha256(path)


def test_the_demo_policy_header_says_its_tokenizer_and_ranges_are_stand_ins():
    adapter = make_adapter(AdapterConfig(model="pi05", variant="demo"))
    adapter.load()
    assert "random-weight policy only" in adapter.checkpoint_provenance["tokenizer"]["source"]
    assert "random-weight policy only" in adapter.checkpoint_provenance["normalization"]["source"]


# X-VLA: `2toINF/X-VLA-Libero` as the release ships it (a transformers remote-code repository), loaded with
# lerobot's `XVLAModel`, lerobot's remap of its weights, its own tokenizer and its image processor.
XVLA = "2toINF/X-VLA-Libero"
XVLA_FILES = {"config.json", "model.safetensors", "preprocessor_config.json", "tokenizer.json", "tokenizer_config.json",
              "vocab.json"}


def test_the_xvla_release_layout_resolves_offline_and_lerobots_remap_names_every_weight(hub_fixture):
    from huggingface_hub import snapshot_download

    from vlaquantbench.hub.checks import weight_shapes
    from vlaquantbench.models.xvla import release

    checkpoint, revision = pinned(hub_fixture, "xvla")
    with offline_cache(hub_fixture["home"]):
        folder = Path(snapshot_download(checkpoint, revision=revision, local_files_only=True))
    assert folder.name == revision and {p.name for p in folder.iterdir()} == XVLA_FILES
    config = json.loads((folder / "config.json").read_text())
    assert config["model_type"] == "xvla" and "type" not in config  # not lerobot's layout
    assert config["auto_map"]["AutoModel"] == "modeling_xvla.XVLA" and config["num_actions"] == 30
    shapes = weight_shapes(folder / "model.safetensors")
    # the remote code's names: vendored Florence-2 (DaViT wrappers, BART under `.model`, a raw projection)
    assert "vlm.image_projection" in shapes and "vlm.language_model.final_logits_bias" in shapes
    assert "vlm.vision_tower.blocks.0.0.spatial_block.window_attn.fn.qkv.weight" in shapes
    assert not [k for k in shapes if k.startswith("model.") or "decoder.layers" in k]
    expected = release.build_model(release.policy_config(config, "cpu", "float32"), device="meta").state_dict()
    renamed = release.lerobot_state({k: torch.empty(s, device="meta") for k, s in shapes.items()})
    assert {k: tuple(v.shape) for k, v in renamed.items()} == {k: tuple(v.shape) for k, v in expected.items()}


def xvla_fault(folder: Path, fault: str) -> None:
    """Break one file of a writable X-VLA snapshot copy."""
    if fault.startswith("missing_"):
        (folder / {"missing_config": "config.json", "missing_image_processor": "preprocessor_config.json"}[fault]).unlink()
    elif fault == "corrupt_config":
        (folder / "config.json").write_text('{"model_type": "xvla", "hidden_size": ')
    elif fault == "config_without_florence":
        config = json.loads((folder / "config.json").read_text())
        del config["florence_config"]["vision_config"]
        (folder / "config.json").write_text(json.dumps(config))
    elif fault == "corrupt_image_processor":
        (folder / "preprocessor_config.json").write_text('{"image_mean": [0.5, ')
    elif fault == "tokenizer":
        for name in ("tokenizer.json", "vocab.json"):
            (folder / name).write_text((folder / name).read_text()[:300])
    else:
        weights = folder / "model.safetensors"
        state = load_file(weights)
        if fault == "weights_missing":
            del state["transformer.action_decoder.bias.weight"]
        else:
            state["vlm.language_model.model.encoder.layers.0.fc1.weight"] = torch.zeros(3, 3)
        weights.unlink()
        save_file(state, weights)


@pytest.mark.parametrize("fault, message", [
    ("missing_config", r"X-VLA config config.json is missing from"),
    ("corrupt_config", r"X-VLA config .*config.json is corrupt"),
    ("config_without_florence", r"X-VLA config .*config.json lacks florence_config.vision_config"),
    ("missing_image_processor", r"image processor file preprocessor_config.json is missing"),
    ("corrupt_image_processor", r"image processor file .*preprocessor_config.json is corrupt"),
    ("tokenizer", rf"tokenizer of {XVLA} \(tokenizer.json, tokenizer_config.json, vocab.json in .*\) does not load"),
    ("weights_missing", r"model.safetensors does not fit the architecture: 1 missing keys: transformer.action_decoder.bias.weight"),
    ("weights_shape", r"model.safetensors does not fit the architecture: wrong shapes: "
                      r"vlm.language_model.encoder.layers.0.fc1.weight \(3, 3\) vs \(128, 64\)"),
])
def test_a_faulty_xvla_release_is_refused_naming_the_file(hub_fixture, tmp_path, fault, message):
    folder = snapshot_copy(hub_fixture, tmp_path, XVLA)
    xvla_fault(folder, fault)
    with pytest.raises(UserError, match=message):
        load(hub_fixture, folder, model="xvla")


def test_an_xvla_snapshot_of_another_revision_is_refused(hub_fixture):
    folder = hub_fixture["repos"][XVLA]["path"]
    with pytest.raises(UserError, match=rf"snapshot {folder} is revision .*, but the config pins revision {'2' * 40}"):
        load(hub_fixture, folder, model="xvla", revision="2" * 40)


def test_xvla_prompts_use_the_releases_tokenizer_and_images_its_processor(hub_fixture):
    from transformers import AutoImageProcessor, AutoTokenizer

    from vlaquantbench.hub.checks import sha256

    folder = Path(hub_fixture["repos"][XVLA]["path"])
    adapter = load(hub_fixture, folder, model="xvla")
    header = adapter.checkpoint_provenance
    assert header["tokenizer"] == {"class": "RobertaTokenizer", "repo": XVLA, "revision": folder.name,
                                   "files": {n: sha256(folder / n) for n in ("tokenizer.json", "tokenizer_config.json", "vocab.json")}}
    processor = AutoImageProcessor.from_pretrained(folder)
    record = header["normalization"]["image_processor"]
    assert (record["sha256"], record["size"], record["mode"]) == (sha256(folder / "preprocessor_config.json"), 224, "bicubic")
    assert record["mean"] == list(processor.image_mean) and record["std"] == list(processor.image_std)
    # The adapter's view of a 224 px frame: (pixel / 255 - mean) / std with the file's numbers, by hand.
    frame = np.random.default_rng(0).integers(0, 256, (224, 224, 3), dtype=np.uint8)
    observation = {"agentview": frame, "wrist": frame}  # a LIBERO observation
    view = adapter._view([observation], "main", adapter.adapter_conventions(observation))[0].numpy()
    by_hand = (frame.astype(np.float64) / 255.0 - np.array(processor.image_mean)) / np.array(processor.image_std)
    np.testing.assert_allclose(view, by_hand.transpose(2, 0, 1), rtol=0, atol=1e-5)
    text = "pick up the black bowl between the plate and the ramekin and place it on the plate"
    assert adapter.tokenizer(text).input_ids == AutoTokenizer.from_pretrained(folder).encode(text)


# OpenVLA-OFT: the four `moojink/openvla-7b-oft-finetuned-libero-<suite>` releases as they ship (transformers
# remote-code repositories), loaded into the architecture built here, with no remote code run.
OFT_SUITES = ("libero_spatial", "libero_object", "libero_goal", "libero_10")


def oft_release(suite):
    from vlaquantbench.models.openvla_oft.release import RELEASES

    return RELEASES[suite]


def load_oft(hub_fixture, folder, suite="libero_spatial", revision=None):
    release = oft_release(suite)
    adapter = make_adapter(AdapterConfig(model="openvla_oft", variant="full", checkpoint=release.repo, suite=suite,
                                         revision=revision or release.revision, checkpoint_dir=str(folder)))
    adapter.load()
    return adapter


@pytest.mark.parametrize("suite", OFT_SUITES)
def test_each_oft_release_resolves_offline_in_its_released_layout_and_loads_strictly(hub_fixture, suite):
    from huggingface_hub import snapshot_download
    from safetensors import safe_open

    release = oft_release(suite)
    with offline_cache(hub_fixture["home"]):
        folder = Path(snapshot_download(release.repo, revision=release.revision, local_files_only=True))
    assert folder.name == release.revision == hub_fixture["repos"][release.repo]["revision"]
    shards = {f"model-0000{i}-of-00004.safetensors" for i in range(1, 5)}
    heads = {f"action_head--{release.step}_checkpoint.pt", f"proprio_projector--{release.step}_checkpoint.pt"}
    assert {p.name for p in folder.iterdir()} == shards | heads | {
        "model.safetensors.index.json", "config.json", "dataset_statistics.json", "preprocessor_config.json",
        "tokenizer.model", "tokenizer.json", "tokenizer_config.json", "vlaquantbench_reduced_widths.json"}
    config = json.loads((folder / "config.json").read_text())
    assert config["model_type"] == "openvla" and config["architectures"] == ["OpenVLAForActionPrediction"]
    assert config["auto_map"] == {"AutoConfig": "configuration_prismatic.OpenVLAConfig",
                                  "AutoModelForVision2Seq": "modeling_prismatic.OpenVLAForActionPrediction"}
    weight_map = json.loads((folder / "model.safetensors.index.json").read_text())["weight_map"]
    assert set(weight_map.values()) == shards and len(weight_map) == 982  # the release's 981 VLA keys + lm_head
    for shard in shards:
        with safe_open(folder / shard, "pt") as f:
            assert set(f.keys()) == {k for k, s in weight_map.items() if s == shard}
    assert "vision_backbone.featurizer.blocks.0.ls1.scale_factor" in weight_map  # timm's gamma, as the remote code names it
    assert "language_model.lm_head.weight" in weight_map and "vision_backbone.fused_featurizer.attn_pool.latent" in weight_map
    assert not [k for k in weight_map if "gamma" in k or k.startswith(("action_head", "proprio_projector"))]
    head = torch.load(folder / f"action_head--{release.step}_checkpoint.pt", weights_only=True)
    assert "module.model.fc2.weight" in head and all(k.startswith("module.") for k in head)
    assert list(json.loads((folder / "dataset_statistics.json").read_text())) == [f"{suite}_no_noops"]

    adapter = load_oft(hub_fixture, folder, suite)  # strict: every key of the files and of the model matched
    assert adapter.checkpoint_provenance["widths"] == "reduced (offline hub fixture)"
    fc2 = adapter.model.action_head.model.fc2.weight
    torch.testing.assert_close(fc2, head["module.model.fc2.weight"], rtol=0, atol=0)
    scale = adapter.model.vision_backbone.featurizer.blocks[0].ls1.gamma
    with safe_open(folder / weight_map["vision_backbone.featurizer.blocks.0.ls1.scale_factor"], "pt") as f:
        torch.testing.assert_close(scale, f.get_tensor("vision_backbone.featurizer.blocks.0.ls1.scale_factor"), rtol=0, atol=0)


def oft_fault(folder: Path, fault: str) -> None:
    """Break one file of a writable OFT snapshot copy (LIBERO-Spatial's)."""
    if fault == "missing_action_head":
        (folder / "action_head--150000_checkpoint.pt").unlink()
    elif fault == "statistics_of_another_suite":
        path = folder / "dataset_statistics.json"
        path.write_text(json.dumps({"libero_goal_no_noops": json.loads(path.read_text())["libero_spatial_no_noops"]}))
    elif fault in ("shard_key_missing", "shard_shape"):
        weight_map = json.loads((folder / "model.safetensors.index.json").read_text())["weight_map"]
        key = "projector.fc3.bias" if fault == "shard_key_missing" else "language_model.model.layers.0.mlp.down_proj.weight"
        shard = folder / weight_map[key]
        state = load_file(shard)
        if fault == "shard_key_missing":
            del state[key]
        else:
            state[key] = state[key][:, :16].contiguous()
        shard.unlink()
        save_file(state, shard)
    elif fault == "head_shape":
        path = folder / "proprio_projector--150000_checkpoint.pt"
        state = torch.load(path, weights_only=True)
        state["module.fc1.weight"] = state["module.fc1.weight"][:, :7].contiguous()  # a 7-D state instead of 8
        path.unlink()
        torch.save(state, path)
    elif fault == "config_of_another_backbone":
        path = folder / "config.json"
        path.write_text(json.dumps({**json.loads(path.read_text()), "timm_model_ids": ["vit_so400m_patch14_siglip_224"]}))
    elif fault == "native_key_names":  # timm's own names instead of the release's
        index = folder / "model.safetensors.index.json"
        content = json.loads(index.read_text())
        content["weight_map"] = {k.replace(".scale_factor", ".gamma"): v for k, v in content["weight_map"].items()}
        index.unlink()
        index.write_text(json.dumps(content))


@pytest.mark.parametrize("fault, message", [
    ("missing_action_head", r"action_head file action_head--\*_checkpoint.pt: .* holds none; the release ships "
                            r"action_head--150000_checkpoint.pt"),
    ("statistics_of_another_suite", r"statistics file .*dataset_statistics.json has no 'libero_spatial_no_noops' "
                                    r"\(has libero_goal_no_noops\)"),
    ("shard_key_missing", r"state dict .*model-0000\d-of-00004.safetensors does not fit the architecture: 1 missing keys: "
                          r"projector.fc3.bias"),
    ("shard_shape", r"state dict .*model-0000\d-of-00004.safetensors does not fit the architecture: wrong shapes: "
                    r"language_model.model.layers.0.mlp.down_proj.weight \(64, 16\) vs \(64, 128\)"),
    ("head_shape", r"state dict .*proprio_projector--150000_checkpoint.pt does not fit the architecture: wrong shapes: "
                   r"fc1.weight \(64, 7\) vs \(64, 8\)"),
    ("config_of_another_backbone", r"OpenVLA-OFT config .*config.json does not describe the OFT architecture: "
                                   r"timm_model_ids \['vit_so400m_patch14_siglip_224'\]"),
    ("native_key_names", r"model.safetensors.index.json does not fit the architecture: 48 missing keys: "
                         r"vision_backbone.featurizer.blocks.0.ls1.scale_factor"),
])
def test_a_faulty_oft_release_is_refused_before_any_rollout_naming_the_file(hub_fixture, tmp_path, fault, message):
    folder = snapshot_copy(hub_fixture, tmp_path, oft_release("libero_spatial").repo)
    oft_fault(folder, fault)
    with pytest.raises(UserError, match=message):
        load_oft(hub_fixture, folder)


def test_an_oft_snapshot_of_another_revision_is_refused(hub_fixture, tmp_path):
    release = oft_release("libero_object")
    other = "3" * 40
    with offline_cache(hub_fixture["home"]), pytest.raises(UserError, match=rf"{release.repo}@{other}.*holds revisions {release.revision}"):
        download_checkpoint("openvla_oft", "full", release.repo, other, tmp_path / "checkpoint.json")
    folder = hub_fixture["repos"][release.repo]["path"]
    with pytest.raises(UserError, match=rf"snapshot {folder} is revision {release.revision}, but the config pins revision {other}"):
        load_oft(hub_fixture, folder, "libero_object", revision=other)


def test_oft_prompts_use_the_releases_sentencepiece_tokenizer_and_actions_its_statistics(hub_fixture):
    import sentencepiece

    from vlaquantbench.hub.checks import sha256
    from vlaquantbench.models.openvla_oft.adapter import prompt

    folder = Path(hub_fixture["repos"][oft_release("libero_goal").repo]["path"])
    adapter = load_oft(hub_fixture, folder, "libero_goal")
    header = adapter.checkpoint_provenance
    names = ("tokenizer.model", "tokenizer.json", "tokenizer_config.json")
    assert header["tokenizer"] == {"class": "LlamaTokenizer", "repo": oft_release("libero_goal").repo,
                                   "revision": folder.name, "files": {n: sha256(folder / n) for n in names}}
    assert header["normalization"]["statistics"]["sha256"] == sha256(folder / "dataset_statistics.json")
    assert header["normalization"]["statistics"]["key"] == "libero_goal_no_noops"
    # The prompt's ids are SentencePiece's own encoding of the release's tokenizer.model (LLaMA-2: <s> 1, byte fallback).
    text = prompt("Put the wine bottle on top of the cabinet")
    pieces = sentencepiece.SentencePieceProcessor(model_file=str(folder / "tokenizer.model"))
    assert adapter.tokenizer(text, add_special_tokens=False).input_ids == pieces.encode(text)
    assert (pieces.id_to_piece(1), pieces.id_to_piece(2), pieces.id_to_piece(3)) == ("<s>", "</s>", "<0x00>")
    # Actions: [-1, 1] -> the statistics' q01/q99 on the masked dimensions; the gripper binarized and inverted.
    stats = json.loads((folder / "dataset_statistics.json").read_text())["libero_goal_no_noops"]["action"]
    normalized = np.linspace(-1, 1, 8 * 7).reshape(8, 7)
    low, high = np.array(stats["q01"]), np.array(stats["q99"])
    actions = adapter._environment_actions(normalized.copy(), adapter_conventions("openvla_oft", "libero"))
    np.testing.assert_allclose(actions[:, :6], ((normalized + 1) / 2 * (high - low) + low)[:, :6], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(actions[:, 6], -np.sign(2 * normalized[:, 6] - 1))
