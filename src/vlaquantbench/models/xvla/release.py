"""The released X-VLA repositories (`2toINF/X-VLA-Libero` and its siblings) as they ship, read with
lerobot 0.6.1's X-VLA classes.

A release is a transformers remote-code repository, not a lerobot one (its hub tree at the pinned
revision):

    config.json               the remote code's `XVLAConfig` (`model_type` "xvla", `auto_map`): head
                              sizes, `num_actions`, `action_mode`, `use_proprio`, and Florence-2's
                              config in Microsoft's remote-code fields (`florence_config`)
    model.safetensors         the remote code's `XVLA` module state: `vlm.*` (Florence-2 in its vendored
                              module layout, text decoder removed) and `transformer.*` (the action head)
    preprocessor_config.json  the image processor: resize to 224, bicubic, ImageNet mean and std
    tokenizer.json, tokenizer_config.json, vocab.json   BART's byte-level BPE tokenizer
    *.py                      the remote code (configuration_/modeling_xvla.py, Florence-2, transformer,
                              action hub, processor), which `trust_remote_code=True` would run

It has no lerobot processor files and no normalization statistics: the LIBERO model predicts
absolute end-effector targets in the units it was trained on, and its only normalization is the
image processor's. lerobot's `XVLAPolicy.from_pretrained` reads lerobot's own layout only (a
config.json with lerobot's `type` field, weights under `model.`), so a release is loaded the way
lerobot converted these checkpoints: the config translated field by field into lerobot's
`XVLAConfig`, lerobot's `XVLAModel` built from it, and the weights renamed by lerobot's own remap of
the vendored Florence-2 layout before a strict load. Nothing from the remote code runs.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from vlaquantbench.errors import UserError
from vlaquantbench.models.xvla.components import PROPRIO_DIM

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
IMAGE_PROCESSOR_FILE = "preprocessor_config.json"
TOKENIZER_FILES = ("tokenizer.json", "tokenizer_config.json", "vocab.json", "merges.txt")
# The remote code's config fields lerobot's `XVLAConfig` has under the same name.
HEAD_FIELDS = ("hidden_size", "depth", "num_heads", "mlp_ratio", "num_domains", "len_soft_prompts", "dim_time",
               "max_len_seq", "use_hetero_proj", "action_mode", "use_proprio")
_VLM_PREFIX = "vlm."  # where the remote code's `XVLA` keeps Florence-2


def read_config(folder: str | Path) -> dict:
    """The release's config.json, refused unless it is an X-VLA config carrying every field the model needs."""
    path = Path(folder) / CONFIG_FILE
    if not path.is_file():
        raise UserError(f"X-VLA config {CONFIG_FILE} is missing from {path.parent}")
    try:
        config = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise UserError(f"X-VLA config {path} is corrupt (not JSON: {err})") from None
    if config.get("model_type") != "xvla":
        raise UserError(f"X-VLA config {path} has model_type {config.get('model_type')!r}, not 'xvla'")
    missing = [f for f in (*HEAD_FIELDS, "num_actions", "florence_config") if f not in config]
    florence = config.get("florence_config") or {}
    missing += [f"florence_config.{f}" for f in ("vision_config", "text_config") if not florence.get(f)]
    if missing:
        raise UserError(f"X-VLA config {path} lacks {', '.join(missing)}")
    return config


def policy_config(release: Mapping[str, Any], device: str, dtype: str):
    """lerobot's `XVLAConfig` for a release config: the same head, chunk and Florence-2 sizes."""
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.xvla.configuration_xvla import XVLAConfig

    image = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 224, 224))
    chunk = int(release["num_actions"])
    return XVLAConfig(
        florence_config=dict(release["florence_config"]),
        chunk_size=chunk,
        n_action_steps=chunk,
        max_state_dim=PROPRIO_DIM,
        device=device,
        dtype=dtype,
        input_features={"observation.images.image": image, "observation.images.image2": image,
                        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(PROPRIO_DIM,))},
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(PROPRIO_DIM,))},
        **{f: release[f] for f in HEAD_FIELDS},
    )


def build_model(config, device: str | torch.device = "cpu"):
    """lerobot's `XVLAModel` (what `XVLAPolicy` wraps as `.model`) for `config`."""
    from lerobot.policies.xvla.modeling_xvla import XVLAModel

    with torch.device(device):
        return XVLAModel(config, config.get_florence_config(), proprio_dim=config.max_state_dim)


def lerobot_state(release_state: Mapping[str, Any]) -> dict[str, Any]:
    """A release's state dict under lerobot's `XVLAModel` names: lerobot's own remap of the vendored
    Florence-2 layout, then the tied token embedding restored under whichever name safetensors dropped
    (as lerobot's `XVLAPolicy.from_pretrained` does). Works on meta tensors as well."""
    from lerobot.policies.xvla.modeling_xvla import _is_vendored_florence_state_dict, _remap_vendored_florence_state_dict

    state = dict(release_state)
    if _is_vendored_florence_state_dict(state, prefix=_VLM_PREFIX):
        state = _remap_vendored_florence_state_dict(state, prefix=_VLM_PREFIX)
    shared, embed = "vlm.language_model.shared.weight", "vlm.language_model.encoder.embed_tokens.weight"
    if shared in state and embed not in state:
        state[embed] = state[shared]
    elif embed in state and shared not in state:
        state[shared] = state[embed]
    return state


def read_image_processor(folder: str | Path) -> tuple[dict, dict]:
    """The release's image processor (transformers' `CLIPImageProcessor`, as X-VLA's processor reads
    it): the size, resampling, mean and std the adapter applies, and the header's record of the file."""
    from transformers import CLIPImageProcessor

    from vlaquantbench.hub.checks import sha256

    path = Path(folder) / IMAGE_PROCESSOR_FILE
    if not path.is_file():
        raise UserError(f"image processor file {IMAGE_PROCESSOR_FILE} is missing from {path.parent}")
    try:
        json.loads(path.read_text())
        processor = CLIPImageProcessor.from_pretrained(path.parent, local_files_only=True)
    except Exception as err:  # JSON errors, transformers' ValueError/OSError/TypeError on bad fields
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise UserError(f"image processor file {path} is corrupt ({reason})") from None
    size = processor.size.get("shortest_edge") or processor.size.get("height")
    if not size or len(processor.image_mean) != 3 or len(processor.image_std) != 3:
        raise UserError(f"image processor file {path} lacks a size or a 3-channel image_mean/image_std")
    # PIL's resampling codes: 2 bilinear, 3 bicubic (torch's interpolate modes of the same name)
    mode = {2: "bilinear", 3: "bicubic"}.get(int(processor.resample))
    if mode is None:
        raise UserError(f"image processor file {path}: resample {processor.resample} is neither bilinear nor bicubic")
    view = {"size": int(size), "mode": mode, "mean": list(processor.image_mean), "std": list(processor.image_std)}
    record = {"file": IMAGE_PROCESSOR_FILE, "sha256": sha256(path), "class": type(processor).__name__, **view,
              "actions": "not normalized: the release predicts absolute end-effector targets and ships no statistics"}
    return view, record


def load_tokenizer(folder: str | Path, checkpoint: str) -> tuple[Any, dict]:
    """BART's tokenizer from the release's own files (transformers' `BartTokenizer`, tokenizers-backed),
    and its provenance (`checks.load_snapshot_tokenizer`)."""
    from transformers import BartTokenizer

    from vlaquantbench.hub.checks import load_snapshot_tokenizer

    return load_snapshot_tokenizer(BartTokenizer, folder, checkpoint, TOKENIZER_FILES)
