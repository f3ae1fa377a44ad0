"""X-VLA's offline hub fixture: `2toINF/X-VLA-Libero` in the layout the release ships (`release`),
at the demo's reduced widths, with seeded random weights.

- config.json: the release's fields (`model_type` "xvla", `architectures`, `auto_map`, the head's
  sizes, `num_actions` 30, `action_mode` ee6d, `use_proprio`, `florence_config` in Microsoft's
  remote-code fields) with the demo's widths, written by transformers' `PretrainedConfig.save_pretrained`.
- model.safetensors: lerobot's `XVLAModel` built from that config, its state dict renamed into the
  remote code's vendored Florence-2 layout (`vendored_state`, the inverse of lerobot's remap; a test
  checks that lerobot's remap gives the native names back exactly) and saved with safetensors.
- preprocessor_config.json: transformers' `CLIPImageProcessor` at 224 px, bicubic, ImageNet mean and
  std, saved by its `save_pretrained`.
- The tokenizer: a byte-level BPE in BART's format (`<s> <pad> </s> <unk>` at ids 0-3, `<mask>` last),
  its vocabulary trained locally on LIBERO's instructions, saved by transformers' `BartTokenizer`,
  plus the `vocab.json` the release carries beside `tokenizer.json`.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import torch

from vlaquantbench.hub.fixture import HubFixture
from vlaquantbench.models.registry import randomize_linears, seeded_build
from vlaquantbench.models.xvla import release
from vlaquantbench.models.xvla.components import CHUNK, DEMO_FLORENCE, DEMO_HEAD

# The release config's fields besides the head's sizes (2toINF's X-VLA config.json).
RELEASE_FIELDS = {
    "_name_or_path": "xvla",
    "architectures": ["XVLA"],
    "auto_map": {"AutoConfig": "configuration_xvla.XVLAConfig", "AutoModel": "modeling_xvla.XVLA"},
    "action_mode": "ee6d",
    "use_proprio": True,
    "num_actions": CHUNK,
    "mlp_ratio": 4.0,
    "num_domains": 30,
    "len_soft_prompts": 32,
    "dim_time": 32,
    "max_len_seq": 512,
    "use_hetero_proj": False,
    "soft_prompt_length": 32,
}
FLORENCE_IDS = {"model_type": "florence2", "bos_token_id": 0, "eos_token_id": 2, "pad_token_id": 1, "ignore_index": -100}
BART_SPECIALS = ("<s>", "<pad>", "</s>", "<unk>")
TOKENIZER_VOCAB = 2048

# Native (lerobot, transformers' Florence2Model) -> vendored (Microsoft's remote code) names in a
# DaViT block, matched after `vlm.vision_tower.blocks.<stage>.<block>.<spatial|channel>_block.`.
_BLOCK = re.compile(r"vlm\.vision_tower\.blocks\.\d+\.\d+\.(spatial_block|channel_block)\.")
_BLOCK_ATTENTION = {"spatial_block": "window_attn", "channel_block": "channel_attn"}
_PREFIXES = (  # outside the blocks, first match wins
    ("vlm.multi_modal_projector.image_proj_norm.", "vlm.image_proj_norm."),
    ("vlm.multi_modal_projector.image_position_embed.", "vlm.image_pos_embed."),
    ("vlm.multi_modal_projector.visual_temporal_embed.", "vlm.visual_temporal_embed."),
    ("vlm.language_model.", "vlm.language_model.model."),
)


def _vendored_block_key(key: str, match: re.Match) -> str:
    attention = _BLOCK_ATTENTION[match.group(1)]
    head, rest = key[: match.end()], key[match.end():]
    for native, vendored in (("conv1.", "conv1.fn.dw."), ("conv2.", "conv2.fn.dw."), ("norm1.", f"{attention}.norm."),
                             (f"{attention}.", f"{attention}.fn."), ("norm2.", "ffn.norm."), ("ffn.", "ffn.fn.net.")):
        if rest.startswith(native):
            return head + vendored + rest[len(native):]
    return key


def vendored_state(state: dict[str, torch.Tensor], vocab_size: int) -> dict[str, torch.Tensor]:
    """An `XVLAModel` state dict under the remote code's names: DaViT's PreNorm/Mlp wrappers, the
    projector's parts at the top of Florence-2, BART inside `language_model.model`, the image
    projection as a raw (in, out) matrix, the tied token embedding once (under `shared`), and the
    vendored language model's generation-only `final_logits_bias`."""
    out = {}
    for key, value in state.items():
        if key == "vlm.language_model.encoder.embed_tokens.weight":
            continue  # tied to `shared`: saved once, as safetensors stores tied tensors
        if key == "vlm.multi_modal_projector.image_projection.weight":
            out["vlm.image_projection"] = value.t().contiguous()
            continue
        if match := _BLOCK.match(key):
            key = _vendored_block_key(key, match)
        elif key.startswith("vlm.vision_tower.convs."):
            key = re.sub(r"^(vlm\.vision_tower\.convs\.\d+\.)conv\.", r"\1proj.", key)
        else:
            key = next((vendored + key[len(native):] for native, vendored in _PREFIXES if key.startswith(native)), key)
        out[key] = value.contiguous()
    out["vlm.language_model.final_logits_bias"] = torch.zeros(1, vocab_size)
    return out


def release_config() -> dict:
    head = {"hidden_size": DEMO_HEAD["hidden_size"], "depth": DEMO_HEAD["depth"], "num_heads": DEMO_HEAD["num_heads"]}
    return {**RELEASE_FIELDS, **head, "florence_config": {**FLORENCE_IDS, **DEMO_FLORENCE}}


def write_config(folder: Path, fields: dict) -> None:
    from transformers import PretrainedConfig

    class ReleasedXVLAConfig(PretrainedConfig):  # the remote code's config class, as transformers saves it
        model_type = "xvla"

    ReleasedXVLAConfig(**fields).save_pretrained(folder)


def write_image_processor(folder: Path) -> None:
    from transformers import CLIPImageProcessor

    CLIPImageProcessor(size={"shortest_edge": 224}, crop_size={"height": 224, "width": 224}, resample=3,
                       image_mean=[0.485, 0.456, 0.406], image_std=[0.229, 0.224, 0.225]).save_pretrained(folder)


def write_bart_tokenizer(folder: Path, corpus: list[str], vocab_size: int = TOKENIZER_VOCAB) -> None:
    """A byte-level BPE in BART's layout, trained on `corpus`; `tokenizer.json`, `tokenizer_config.json`, `vocab.json`."""
    from tokenizers import Tokenizer, models, pre_tokenizers, trainers
    from transformers import BartTokenizer

    trainer_model = Tokenizer(models.BPE())
    trainer_model.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    trainer_model.train_from_iterator(corpus, trainers.BpeTrainer(
        vocab_size=vocab_size, special_tokens=list(BART_SPECIALS), initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        show_progress=False))
    trained = json.loads(trainer_model.to_str())["model"]
    merges = [tuple(m.split(" ", 1)) if isinstance(m, str) else tuple(m) for m in trained["merges"]]
    tokenizer = BartTokenizer(vocab=trained["vocab"], merges=merges)  # adds <mask> after the vocabulary
    tokenizer.save_pretrained(folder)
    (folder / "vocab.json").write_text(json.dumps(tokenizer.get_vocab(), ensure_ascii=False))


def write_checkpoint(folder: Path, seed: int) -> None:
    from safetensors.torch import save_file

    from vlaquantbench.envs.libero import all_instructions
    from vlaquantbench.hub.tokenizer import training_corpus

    fields = release_config()
    config = release.policy_config(fields, device="cpu", dtype="float32")
    model = seeded_build(lambda: release.build_model(config), torch.device("cpu"), seed)
    randomize_linears(model, seed)
    folder.mkdir(parents=True, exist_ok=True)
    vocab_size = fields["florence_config"]["text_config"]["vocab_size"]
    save_file(vendored_state(model.state_dict(), vocab_size), folder / release.WEIGHTS_FILE, metadata={"format": "pt"})
    write_config(folder, fields)
    write_image_processor(folder)
    write_bart_tokenizer(folder, training_corpus(all_instructions()))  # the release's LIBERO prompts


FIXTURE = HubFixture(write_checkpoint=write_checkpoint)
