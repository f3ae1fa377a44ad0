"""OpenVLA-OFT's offline hub fixture: the four `moojink/openvla-7b-oft-finetuned-libero-<suite>`
repositories in the layout the releases ship (`release`), at their pinned revisions, at the demo's
reduced widths with seeded random weights, and without their remote code.

- config.json: the remote code's `OpenVLAConfig` fields (`model_type` "openvla", `architectures`,
  `auto_map`, the fused backbone's timm ids, `arch_specifier`, LLaMA-2's `text_config` at the demo's widths).
- model-0000<i>-of-00004.safetensors + model.safetensors.index.json: `OpenVLAOFT`'s VLA weights under the
  release's names, split into shards by huggingface_hub's `split_torch_state_dict_into_shards`.
- action_head--<step>_checkpoint.pt, proprio_projector--<step>_checkpoint.pt: the two heads' state dicts
  with DistributedDataParallel's `module.` prefix, saved with `torch.save`, named with each release's step.
- dataset_statistics.json: the suite's `<suite>_no_noops` entry (action and proprio mean, std, max, min,
  q01, q99; the action mask leaving the gripper unnormalized), from a seeded sample of LIBERO-like values.
- The tokenizer: a SentencePiece BPE model in LLaMA-2's layout (`<unk> <s> </s>` at ids 0-2, 256 byte
  fallback pieces, split digits, a dummy prefix, no normalization) trained by the `sentencepiece`
  package on LIBERO's instructions in OFT's prompt frame, saved as `tokenizer.model` and by transformers'
  `LlamaTokenizer` (`tokenizer.json`, `tokenizer_config.json`) with `<PAD>` added after the vocabulary.
- preprocessor_config.json: the remote code's image processor's class, `auto_map` and per-backbone sizes,
  means and standard deviations.
- `release.REDUCED_WIDTHS_FILE`: the vision backbones' reduced widths, which config.json cannot express.
"""

from __future__ import annotations

import functools
import io
import json
from pathlib import Path

import torch

from vlaquantbench.hub.fixture import HubFixture
from vlaquantbench.models.openvla_oft import release
from vlaquantbench.models.openvla_oft.adapter import prompt
from vlaquantbench.models.openvla_oft.architecture import DEMO, DINOV2, IMAGE_SIZE, SIGLIP, OpenVLAOFT
from vlaquantbench.models.registry import demo_build

PIECES = DEMO.vocab - 64  # SentencePiece vocabulary; `<PAD>` follows, and the LLM pads its vocabulary to a multiple of 64
PAD = "<PAD>"
SHARDS = 4
AUTO_MAP = {"AutoConfig": "configuration_prismatic.OpenVLAConfig",
            "AutoModelForVision2Seq": "modeling_prismatic.OpenVLAForActionPrediction"}
PROCESSOR_AUTO_MAP = {"AutoImageProcessor": "processing_prismatic.PrismaticImageProcessor",
                      "AutoProcessor": "processing_prismatic.PrismaticProcessor"}
IMAGE_STATISTICS = {"means": [[0.485, 0.456, 0.406], [0.5, 0.5, 0.5]], "stds": [[0.229, 0.224, 0.225], [0.5, 0.5, 0.5]]}


@functools.cache
def sentencepiece_model() -> bytes:
    """LLaMA-2's trainer settings on OFT's prompts of every LIBERO instruction (trained once per process)."""
    import sentencepiece

    from vlaquantbench.envs.libero import all_instructions

    model = io.BytesIO()
    sentencepiece.SentencePieceTrainer.train(
        sentence_iterator=iter([prompt(text) for text in all_instructions()]), model_writer=model,
        model_type="bpe", vocab_size=PIECES, byte_fallback=True, split_digits=True, unk_id=0, bos_id=1, eos_id=2,
        pad_id=-1, add_dummy_prefix=True, normalization_rule_name="identity", remove_extra_whitespaces=False,
        allow_whitespace_only_pieces=True, character_coverage=1.0, minloglevel=2)
    return model.getvalue()


def write_tokenizer(folder: Path) -> int:
    """tokenizer.model, then transformers' files of the same tokenizer plus `<PAD>`; returns `<PAD>`'s id."""
    from transformers import LlamaTokenizer

    (folder / "tokenizer.model").write_bytes(sentencepiece_model())
    tokenizer = LlamaTokenizer.from_pretrained(folder, legacy=False)
    tokenizer.add_special_tokens({"pad_token": PAD})
    tokenizer.save_pretrained(folder)
    config_path = folder / "tokenizer_config.json"
    config = json.loads(config_path.read_text())
    config["auto_map"] = {"AutoProcessor": PROCESSOR_AUTO_MAP["AutoProcessor"]}
    config_path.write_text(json.dumps(config, indent=2) + "\n")
    return tokenizer.pad_token_id


def release_config(pad_token_id: int) -> dict:
    from transformers import LlamaConfig

    text = LlamaConfig(vocab_size=DEMO.vocab, hidden_size=DEMO.llm_dim, intermediate_size=DEMO.llm_mlp,
                       num_hidden_layers=32, num_attention_heads=DEMO.llm_heads, num_key_value_heads=DEMO.llm_heads,
                       max_position_embeddings=2048, pad_token_id=pad_token_id)
    return {
        "architectures": ["OpenVLAForActionPrediction"], "auto_map": AUTO_MAP, "model_type": "openvla",
        "vision_backbone_id": "dinosiglip-vit-so-224px", "llm_backbone_id": "llama2-7b-pure",
        "arch_specifier": "no-align+fused-gelu-mlp", "use_fused_vision_backbone": True,
        "image_resize_strategy": "resize-naive", "timm_model_ids": [DINOV2, SIGLIP],
        "timm_override_act_layers": [None, None], "image_sizes": [IMAGE_SIZE, IMAGE_SIZE],
        "hf_llm_id": "meta-llama/Llama-2-7b-hf", "llm_max_length": 2048, "pad_token_id": pad_token_id,
        "pad_to_multiple_of": 64, "output_projector_states": False, "n_action_bins": 256, "norm_stats": None,
        "text_config": text.to_dict(), "torch_dtype": "float32",
    }


def dataset_statistics(suite: str, seed: int) -> dict:
    """The `<suite>_no_noops` entry, from the seeded LIBERO-like sample the pi fixtures' statistics use."""
    from vlaquantbench.models.pi_family_fixture import dataset_stats

    sample = dataset_stats(seed)

    def listed(stats: dict[str, torch.Tensor]) -> dict[str, list[float]]:
        return {name: stats[name].tolist() for name in ("mean", "std", "max", "min", "q01", "q99")}

    action = {**listed(sample["action"]), "mask": [True] * 6 + [False]}
    return {release.statistics_key(suite): {"action": action, "proprio": listed(sample["observation.state"])}}


def write_weights(folder: Path, model: OpenVLAOFT, step: int) -> None:
    from huggingface_hub import split_torch_state_dict_into_shards
    from safetensors.torch import save_file

    state = {k: v.contiguous() for k, v in model.state_dict().items()}
    for part in release.HEADS:
        head = {release.DDP_PREFIX + k.removeprefix(f"{part}."): v for k, v in state.items() if k.startswith(f"{part}.")}
        torch.save(head, folder / release.head_file(part, step))
    body = {release.released_name(k): v for k, v in state.items() if not k.startswith(release.HEADS)}
    total = sum(v.numel() * v.element_size() for v in body.values())
    split = split_torch_state_dict_into_shards(body, filename_pattern="model{suffix}.safetensors",
                                               max_shard_size=-(-total // SHARDS) + max(v.nbytes for v in body.values()))
    for shard, names in split.filename_to_tensors.items():
        save_file({name: body[name] for name in names}, folder / shard, metadata={"format": "pt"})
    index = {"metadata": {"total_size": total}, "weight_map": split.tensor_to_filename}
    (folder / release.INDEX_FILE).write_text(json.dumps(index, indent=2, sort_keys=True) + "\n")


@functools.cache
def demo_model(seed: int) -> OpenVLAOFT:
    """The weights all four releases share (built once: random weights say nothing per suite either way)."""
    return demo_build(lambda: OpenVLAOFT(DEMO), torch.device("cpu"), seed)


def write_release(suite: str, folder: Path, seed: int) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    write_weights(folder, demo_model(seed), release.RELEASES[suite].step)
    pad_token_id = write_tokenizer(folder)
    (folder / release.CONFIG_FILE).write_text(json.dumps(release_config(pad_token_id), indent=2) + "\n")
    (folder / release.STATISTICS_FILE).write_text(json.dumps(dataset_statistics(suite, seed), indent=2) + "\n")
    processor = {"auto_map": PROCESSOR_AUTO_MAP, "image_processor_type": "PrismaticImageProcessor",
                 "processor_class": "PrismaticProcessor", "use_fused_vision_backbone": True,
                 "image_resize_strategy": "resize-naive", "input_sizes": [[3, IMAGE_SIZE, IMAGE_SIZE]] * 2,
                 "interpolations": ["bicubic", "bicubic"], **IMAGE_STATISTICS}
    (folder / "preprocessor_config.json").write_text(json.dumps(processor, indent=2) + "\n")
    widths = {"dino": list(DEMO.dino), "siglip": list(DEMO.siglip)}
    (folder / release.REDUCED_WIDTHS_FILE).write_text(json.dumps(widths, indent=2, sort_keys=True) + "\n")


FIXTURE = HubFixture(releases={r.repo: (r.revision, functools.partial(write_release, suite))
                               for suite, r in release.RELEASES.items()})
