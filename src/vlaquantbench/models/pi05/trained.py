"""A pi0.5 policy trained here from scratch: lerobot's `PI05Policy` at reduced widths with every
module name, depth and component scope of the released model, and a word-level task tokenizer.

`build_policy` makes the policy and its processor pipelines for a LeRobotDataset's features and
statistics exactly as lerobot's training script does (`make_policy`, `make_pi05_pre_post_processors`),
with two differences lerobot has no setting for: the widths (`reduced_widths`, the vocabulary sized
to the tokenizer) and the tokenizer the preprocessor loads by repository id (lerobot's factory names
PaliGemma's). `save` writes what `save_pretrained` writes, plus `REDUCED_WIDTHS_FILE`, so the folder
loads through the same path as a released checkpoint (`PiFamilyAdapter._load_checkpoint`).
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any
from unittest import mock

from vlaquantbench.models.paligemma_family import REDUCED_WIDTHS_FILE, reduced_widths


def trained_widths(widths: dict[str, Any], vocab_size: int) -> dict[str, Any]:
    """`reduced_widths`' sizes from a training config's `widths` (vision, gemma_2b, gemma_300m):
    full depths, grouped-query attention with one KV head as released, the vocabulary of the tokenizer."""
    vlm, expert, vision = widths["gemma_2b"], widths["gemma_300m"], widths["vision"]
    # The expert attends jointly with the VLM, so it shares the VLM's heads and head size.
    attention = dict(depth=18, num_heads=8, num_kv_heads=1, head_dim=vlm["head_dim"])
    return {
        "gemma_2b": dict(width=vlm["width"], mlp_dim=vlm["mlp_dim"], **attention),
        "gemma_300m": dict(width=expert["width"], mlp_dim=expert["mlp_dim"], **attention),
        "vision": dict(hidden_size=vision["hidden_size"], intermediate_size=vision["intermediate_size"],
                       num_attention_heads=vision["num_attention_heads"], num_hidden_layers=27),
        "vocab_size": vocab_size,
    }


def policy_config(dataset_meta, policy: dict[str, Any], device: str):
    """The `PI05Config` of a training config's `policy` section for a dataset: the camera's own
    resolution, the state's size as the prompt's state length, lerobot's optimizer and scheduler
    presets with the section's learning-rate schedule (from-scratch training, not lerobot's
    fine-tuning one)."""
    from lerobot.configs import NormalizationMode
    from lerobot.policies.pi05.configuration_pi05 import PI05Config

    cameras = [k for k, f in dataset_meta.features.items() if f["dtype"] in ("image", "video")]
    if len(cameras) != 1:
        raise ValueError(f"the dataset has cameras {cameras}; the trained pi0.5 reads exactly one")
    height, width = dataset_meta.features[cameras[0]]["shape"][:2]
    state_dim = dataset_meta.features["observation.state"]["shape"][0]
    return PI05Config(
        device=device,
        dtype="float32",
        image_resolution=(height, width),
        max_state_dim=state_dim,
        chunk_size=policy["chunk_size"],
        n_action_steps=policy["n_action_steps"],
        tokenizer_max_length=policy["tokenizer_max_length"],
        normalization_mapping={k: NormalizationMode(v) for k, v in policy["normalization"].items()},
        optimizer_lr=policy["lr"],
        scheduler_warmup_steps=policy["warmup_steps"],
        scheduler_decay_steps=policy["decay_steps"],
        scheduler_decay_lr=policy["decay_lr"],
    )


def build_policy(dataset_meta, policy: dict[str, Any], tokenizer_repo: str, tokenizer, device: str):
    """(policy, preprocessor, postprocessor, widths) for `dataset_meta` (a LeRobotDatasetMetadata):
    lerobot's `make_policy` at the section's widths, and lerobot's pi0.5 processors carrying the
    dataset's statistics, with `tokenizer` (saved as repository `tokenizer_repo`) in the tokenizer step."""
    from lerobot.policies.factory import make_policy
    from lerobot.policies.pi05 import modeling_pi05, processor_pi05

    from vlaquantbench.models.pi05.task_tokenizer import padded_vocab_size

    config = policy_config(dataset_meta, policy, device)
    widths = trained_widths(policy["widths"], padded_vocab_size(tokenizer))
    with reduced_widths(modeling_pi05, widths):
        model = make_policy(config, ds_meta=dataset_meta)
    # lerobot's factory hard-codes PaliGemma's repository in its tokenizer step; the step built here
    # holds the task tokenizer and saves `tokenizer_repo` as the name it is loaded by.
    tokenizer_step = functools.partial(_named_tokenizer_step, processor_pi05.TokenizerProcessorStep, tokenizer_repo, tokenizer)
    with mock.patch.object(processor_pi05, "TokenizerProcessorStep", tokenizer_step):
        preprocessor, postprocessor = processor_pi05.make_pi05_pre_post_processors(model.config, dataset_meta.stats)
    return model, preprocessor, postprocessor, widths


def _named_tokenizer_step(step_cls, tokenizer_repo: str, tokenizer, **kwargs):
    kwargs.pop("tokenizer_name")
    step = step_cls(tokenizer=tokenizer, **kwargs)
    # lerobot saves a step's tokenizer_name only when the step loaded it by name; this one is saved
    # under that name next to the checkpoint, so the saved step loads it back by name.
    step.tokenizer_name, step.tokenizer = tokenizer_repo, None
    return step


def save(folder: str | Path, model, preprocessor, postprocessor, widths: dict[str, Any]) -> Path:
    """`save_pretrained` of the policy and both processors into `folder`, with the widths it loads at."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    model.save_pretrained(folder)
    preprocessor.save_pretrained(folder)
    postprocessor.save_pretrained(folder)
    (folder / REDUCED_WIDTHS_FILE).write_text(json.dumps(widths, indent=2, sort_keys=True) + "\n")
    return folder
