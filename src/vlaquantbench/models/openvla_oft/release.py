"""The released OpenVLA-OFT LIBERO repositories (`moojink/openvla-7b-oft-finetuned-libero-<suite>`), as
they ship, read without their remote code.

A release is a transformers remote-code repository (its hub tree at the pinned revision):

    config.json                    the remote code's `OpenVLAConfig` (`model_type` "openvla", `auto_map`
                                   into configuration_/modeling_prismatic.py): the fused DINOv2 + SigLIP
                                   backbone's timm ids, the projector's `arch_specifier`, and LLaMA-2's
                                   `text_config` (widths, depth, vocabulary padded to a multiple of 64)
    model-0000<i>-of-00004.safetensors, model.safetensors.index.json
                                   the merged (LoRA folded in) VLA: `vision_backbone.featurizer.*`
                                   (DINOv2), `vision_backbone.fused_featurizer.*` (SigLIP), `projector.*`,
                                   `language_model.*` (LLaMA-2, `lm_head` included); timm's LayerScale
                                   weights under `ls<i>.scale_factor`, the name the remote code gives
                                   timm's `gamma` (transformers renames parameters called gamma on load)
    action_head--<step>_checkpoint.pt, proprio_projector--<step>_checkpoint.pt
                                   torch state dicts of the L1 head and the proprio projector, saved from
                                   DistributedDataParallel: every key starts with `module.`
    dataset_statistics.json        {"<suite>_no_noops": {"action": {mean, std, max, min, q01, q99, mask},
                                   "proprio": {...}, "num_transitions", "num_trajectories"}}: the bounds
                                   actions are unnormalized with and the state normalized with
    tokenizer.model, tokenizer.json, tokenizer_config.json, special_tokens_map.json, added_tokens.json
                                   LLaMA-2's SentencePiece tokenizer plus `<PAD>` (id 32000)
    preprocessor_config.json       the remote code's image processor (`auto_map`)
    *.py, lora_adapter/, README.md the remote code, the unmerged LoRA weights, the model card

The model is built from `architecture.OpenVLAOFT` at the widths config.json gives, on the meta device,
and the files above are checked (keys and shapes from the safetensors headers and the `.pt` files,
the suite's statistics, the tokenizer) before the weights load strictly. Nothing from the remote code runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from vlaquantbench.errors import UserError
from vlaquantbench.hub.checks import load_json, sha256
from vlaquantbench.models.openvla_oft.architecture import ACTION_DIM, DINOV2, PROPRIO_DIM, SIGLIP, OFTSizes


@dataclass(frozen=True)
class Release:
    repo: str
    revision: str  # the commit the cache snapshot of each repository is named by
    step: int  # training step in the names of the `.pt` files


# The four per-suite releases. Spatial's revision is the one the paper records (its App. on checkpoints);
# the others are the snapshot commits of those repositories as public evaluation setups name them.
RELEASES = {
    "libero_spatial": Release("moojink/openvla-7b-oft-finetuned-libero-spatial", "6d0231af0e48c5985f1ff86908f4674b84bc049b", 150000),
    "libero_object": Release("moojink/openvla-7b-oft-finetuned-libero-object", "4c89574e1c538b6c102f43f0526d60a9d3650148", 150000),
    "libero_goal": Release("moojink/openvla-7b-oft-finetuned-libero-goal", "c2d0f9fbbd82674683b397ff923168a12f6a307b", 50000),
    "libero_10": Release("moojink/openvla-7b-oft-finetuned-libero-10", "95220f9a3421a7ff12d4218e73d09ade830fa9a3", 150000),
}
CONFIG_FILE = "config.json"
INDEX_FILE = "model.safetensors.index.json"
STATISTICS_FILE = "dataset_statistics.json"
TOKENIZER_FILES = ("tokenizer.model", "tokenizer.json", "tokenizer_config.json", "special_tokens_map.json", "added_tokens.json")
HEADS = ("proprio_projector", "action_head")  # the parts saved as `.pt` files, as the model names them
DDP_PREFIX = "module."
# A snapshot holding this file was written at reduced vision widths (the offline hub fixture): config.json
# names the backbones by timm id only, which fixes their widths; released repositories have no such file.
REDUCED_WIDTHS_FILE = "vlaquantbench_reduced_widths.json"
_LAYER_SCALE = ((".ls1.gamma", ".ls1.scale_factor"), (".ls2.gamma", ".ls2.scale_factor"))


def statistics_key(suite: str) -> str:
    return f"{suite}_no_noops"


def head_file(part: str, step: int) -> str:
    return f"{part}--{step}_checkpoint.pt"


def released_name(key: str) -> str:
    """A key of `OpenVLAOFT`'s state dict under the release's name (LayerScale `gamma` -> `scale_factor`)."""
    for native, released in _LAYER_SCALE:
        key = key.replace(native, released)
    return key


def native_name(key: str) -> str:
    for native, released in _LAYER_SCALE:
        key = key.replace(released, native)
    return key


def read_sizes(folder: str | Path) -> tuple[OFTSizes, bool]:
    """The widths config.json gives (LLaMA-2's from `text_config`; the vision backbones' from their timm
    ids, or from `REDUCED_WIDTHS_FILE` where the snapshot holds one), and whether they are reduced;
    refused unless config.json describes the architecture `OpenVLAOFT` builds."""
    path = Path(folder) / CONFIG_FILE
    config = load_json(path, "OpenVLA-OFT config")
    if config.get("model_type") != "openvla":
        raise UserError(f"OpenVLA-OFT config {path} has model_type {config.get('model_type')!r}, not 'openvla'")
    expected = {"timm_model_ids": [DINOV2, SIGLIP], "use_fused_vision_backbone": True,
                "arch_specifier": "no-align+fused-gelu-mlp", "image_sizes": [224, 224]}
    wrong = [f"{field} {config.get(field)!r} (the architecture has {value!r})" for field, value in expected.items()
             if config.get(field) != value]
    text = config.get("text_config") or {}
    fields = ("hidden_size", "intermediate_size", "num_attention_heads", "vocab_size", "num_hidden_layers")
    wrong += [f"text_config.{field} missing" for field in fields if not isinstance(text.get(field), int)]
    if not wrong and text["num_hidden_layers"] != 32:
        wrong.append(f"text_config.num_hidden_layers {text['num_hidden_layers']} (the architecture has 32)")
    if wrong:
        raise UserError(f"OpenVLA-OFT config {path} does not describe the OFT architecture: {'; '.join(wrong)}")
    vision = {"dino": OFTSizes.dino, "siglip": OFTSizes.siglip}
    reduced_path = Path(folder) / REDUCED_WIDTHS_FILE
    if reduced_path.exists():
        vision = {name: tuple(value) for name, value in load_json(reduced_path, "OpenVLA-OFT widths file").items()}
    sizes = OFTSizes(llm_dim=text["hidden_size"], llm_mlp=text["intermediate_size"], llm_heads=text["num_attention_heads"],
                     vocab=text["vocab_size"], **vision)
    return sizes, reduced_path.exists() or sizes != OFTSizes()


def read_statistics(folder: str | Path, suite: str) -> tuple[dict, dict]:
    """The suite's entry of dataset_statistics.json (action and proprio q01/q99, the action mask) and
    the header's record of the file; refused naming the file and the keys it has."""
    path = Path(folder) / STATISTICS_FILE
    statistics = load_json(path, "OpenVLA-OFT statistics file")
    key = statistics_key(suite)
    if not isinstance(statistics, dict) or key not in statistics:
        has = ", ".join(statistics) if isinstance(statistics, dict) else type(statistics).__name__
        raise UserError(f"OpenVLA-OFT statistics file {path} has no {key!r} (has {has}): the checkpoint was not "
                        f"trained on {suite}")
    entry = statistics[key]
    for feature, size in (("action", ACTION_DIM), ("proprio", PROPRIO_DIM)):
        for stat in ("q01", "q99"):
            value = (entry.get(feature) or {}).get(stat)
            if not isinstance(value, list) or len(value) != size:
                raise UserError(f"OpenVLA-OFT statistics file {path}: {key}.{feature}.{stat} is not a list of {size} numbers")
    record = {"file": STATISTICS_FILE, "sha256": sha256(path), "key": key,
              "action": "q01/q99 bounds on the masked dimensions", "proprio": "q01/q99 bounds"}
    return entry, record


def load_tokenizer(folder: str | Path, checkpoint: str) -> tuple[Any, dict]:
    """LLaMA-2's tokenizer from the release's own files (transformers' `LlamaTokenizer`; `AutoTokenizer`
    would read config.json's remote-code `auto_map`), and its provenance (`checks.load_snapshot_tokenizer`);
    refused unless it has LLaMA-2's special-token ids, which the adapter's prompt frame uses."""
    from transformers import LlamaTokenizer

    from vlaquantbench.hub.checks import load_snapshot_tokenizer

    tokenizer, record = load_snapshot_tokenizer(LlamaTokenizer, folder, checkpoint, TOKENIZER_FILES)
    if len(tokenizer) <= 2 or tokenizer.bos_token_id != 1 or tokenizer.eos_token_id != 2:
        raise UserError(f"tokenizer of {checkpoint} in {folder} is not LLaMA-2's layout (<s> 1, </s> 2): it has "
                        f"{len(tokenizer)} tokens, bos {tokenizer.bos_token_id}, eos {tokenizer.eos_token_id}")
    return tokenizer, record


def _head_path(folder: Path, part: str, checkpoint: str | None) -> Path:
    files = sorted(folder.glob(f"{part}--*_checkpoint.pt"))
    known = {r.repo: r for r in RELEASES.values()}.get(checkpoint or "")
    if len(files) != 1:
        shipped = f"; the release ships {head_file(part, known.step)}" if known else ""
        found = ", ".join(p.name for p in files) if files else "none"
        raise UserError(f"OpenVLA-OFT {part} file {part}--*_checkpoint.pt: {folder} must hold exactly one, holds {found}{shipped}")
    return files[0]


def _load_head(path: Path) -> dict[str, torch.Tensor]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception as err:  # pickle, zip and unpickler errors alike
        raise UserError(f"OpenVLA-OFT head file {path} is corrupt ({type(err).__name__}: {err})") from None
    if not isinstance(state, dict):
        raise UserError(f"OpenVLA-OFT head file {path} holds a {type(state).__name__}, not a state dict")
    return {k.removeprefix(DDP_PREFIX): v for k, v in state.items()}


def load_state(folder: str | Path, expected: dict[str, tuple[int, ...]], checkpoint: str | None) -> dict[str, torch.Tensor]:
    """The release's weights under `OpenVLAOFT`'s names, after checking every file against the
    architecture's keys and shapes (`expected`): the index and each shard it names (safetensors headers
    first, so a misfit is refused before any tensor is read), then each `.pt` file."""
    from safetensors.torch import load_file

    from vlaquantbench.hub.checks import check_state_dict_fits, weight_shapes

    folder = Path(folder)
    heads = {part: _head_path(folder, part, checkpoint) for part in HEADS}
    body = {released_name(k): shape for k, shape in expected.items() if not k.startswith(HEADS)}
    index_path = folder / INDEX_FILE
    weight_map = (load_json(index_path, "OpenVLA-OFT weights index") or {}).get("weight_map")
    if not isinstance(weight_map, dict):
        raise UserError(f"OpenVLA-OFT weights index {index_path} has no weight_map")
    check_state_dict_fits({k: body.get(k, ()) for k in weight_map}, body, index_path)
    for shard in sorted(set(weight_map.values())):
        named = {k: body[k] for k, file in weight_map.items() if file == shard}
        check_state_dict_fits(weight_shapes(folder / shard), named, folder / shard)
    state = {}
    for part, path in heads.items():
        weights = _load_head(path)
        part_expected = {k.removeprefix(f"{part}."): shape for k, shape in expected.items() if k.startswith(f"{part}.")}
        check_state_dict_fits({k: tuple(v.shape) for k, v in weights.items()}, part_expected, path)
        state.update({f"{part}.{k}": v for k, v in weights.items()})
    for shard in sorted(set(weight_map.values())):
        state.update({native_name(k): v for k, v in load_file(folder / shard).items()})
    return state
