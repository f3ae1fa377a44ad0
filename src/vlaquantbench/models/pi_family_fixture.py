"""The offline hub fixture of a pi-family checkpoint (`vqb hub-fixture`): what lerobot 0.6.1 writes
for a LIBERO-finetuned `PI05Policy`/`PI0Policy`, at reduced widths.

The policy is built with LIBERO's features (two 256 px cameras `image`/`image2`, 8-D state, 7-D
action) and seeded random weights, and saved with the policy's own `save_pretrained` (config.json,
model.safetensors). Its processor pipelines are lerobot's `make_<policy>_pre_post_processors`,
saved with their `save_pretrained` (policy_{pre,post}processor.json plus the normalizer and
unnormalizer state files): their tokenizer step names PaliGemma's tokenizer repository, which the
fixture holds too, and their statistics are computed from a seeded sample of LIBERO-like states and
actions. `REDUCED_WIDTHS_FILE` records the widths the folder loads at.
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import numpy as np
import torch

from vlaquantbench.hub.tokenizer import REPO_ID as PALIGEMMA_TOKENIZER
from vlaquantbench.models.paligemma_family import DEMO_WIDTHS, REDUCED_WIDTHS_FILE, reduced_widths
from vlaquantbench.models.registry import randomize_linears
from vlaquantbench.models.registry import seeded_build

# LIBERO's observation and action layout as the released LIBERO checkpoints declare it.
CAMERAS = ("observation.images.image", "observation.images.image2")
CAMERA_SHAPE = (3, 256, 256)
STATE_DIM, ACTION_DIM = 8, 7
# Centres and spreads of the sample the statistics are computed from: end-effector position (m),
# axis-angle (rad), gripper fingers (m); delta actions in [-1, 1] with a binary gripper.
_STATE_MEAN = [-0.05, 0.03, 1.0, 3.0, -0.1, -0.05, 0.025, -0.025]
_STATE_STD = [0.1, 0.15, 0.1, 0.2, 0.3, 0.2, 0.01, 0.01]
_ACTION_MEAN = [0.05, 0.1, -0.1, 0.0, 0.0, -0.01, -0.1]
_ACTION_STD = [0.3, 0.35, 0.4, 0.05, 0.07, 0.08, 0.99]
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}


def feature_stats(mean: list[float], std: list[float], seed: int, samples: int = 4096) -> dict[str, torch.Tensor]:
    """lerobot's per-feature statistics (mean, std, min, max, quantiles, count) of a seeded sample."""
    rng = np.random.default_rng(seed)
    x = rng.normal(mean, std, size=(samples, len(mean))).astype(np.float32)
    stats = {"mean": x.mean(0), "std": x.std(0), "min": x.min(0), "max": x.max(0)}
    stats |= {name: np.quantile(x, q, axis=0) for name, q in QUANTILES.items()}
    stats = {k: torch.from_numpy(np.asarray(v, dtype=np.float32)) for k, v in stats.items()}
    return stats | {"count": torch.tensor([samples])}


def dataset_stats(seed: int) -> dict[str, dict[str, torch.Tensor]]:
    return {
        "observation.state": feature_stats(_STATE_MEAN, _STATE_STD, seed),
        "action": feature_stats(_ACTION_MEAN, _ACTION_STD, seed + 1),
    }


def write_pi_checkpoint(folder: Path, adapter_class: type, make_processors: str, normalization: dict, seed: int) -> None:
    """Save a reduced-width policy of `adapter_class`'s lerobot classes and its processors into `folder`.

    `make_processors` is lerobot's factory ("module:function"); `normalization` the policy config's
    `normalization_mapping` (mode per feature type). Needs PaliGemma's tokenizer in the active cache.
    """
    from lerobot.configs import FeatureType, NormalizationMode, PolicyFeature

    lib = importlib.import_module(adapter_class.policy_module)
    policy_cls = getattr(lib, adapter_class.policy_class)
    modeling = importlib.import_module(policy_cls.__module__)
    camera = PolicyFeature(type=FeatureType.VISUAL, shape=CAMERA_SHAPE)
    config = getattr(lib, adapter_class.config_class)(
        device="cpu",
        dtype="float32",
        input_features={
            **dict.fromkeys(CAMERAS, camera),
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,))},
        normalization_mapping={k: NormalizationMode(v) for k, v in normalization.items()},
    )
    with reduced_widths(modeling):
        policy = seeded_build(lambda: policy_cls(config), torch.device("cpu"), seed)
    randomize_linears(policy.model, seed)  # lerobot zero-initialises the adaRMS modulations
    folder.mkdir(parents=True, exist_ok=True)
    policy.save_pretrained(folder)
    (folder / REDUCED_WIDTHS_FILE).write_text(json.dumps(DEMO_WIDTHS, indent=2, sort_keys=True) + "\n")
    module, factory = make_processors.split(":")
    preprocessor, postprocessor = getattr(importlib.import_module(module), factory)(config, dataset_stats(seed))
    tokenizer_steps = [s for s in preprocessor.steps if getattr(s, "tokenizer_name", None)]
    if [s.tokenizer_name for s in tokenizer_steps] != [PALIGEMMA_TOKENIZER]:
        raise RuntimeError(f"{factory} no longer loads the tokenizer {PALIGEMMA_TOKENIZER} the fixture provides")
    preprocessor.save_pretrained(folder)
    postprocessor.save_pretrained(folder)


MEAN_STD = {"VISUAL": "IDENTITY", "STATE": "MEAN_STD", "ACTION": "MEAN_STD"}


def write_released_tokenizer(folder: Path) -> Path:
    """PaliGemma's tokenizer, trained on the prompts of the released pi checkpoints (LIBERO's instructions)."""
    from vlaquantbench.envs.libero import all_instructions
    from vlaquantbench.hub.tokenizer import training_corpus, write_paligemma_tokenizer

    return write_paligemma_tokenizer(folder, training_corpus(all_instructions()))


def pi_fixture(adapter_class: type, make_processors: str, normalization: dict = MEAN_STD):
    """The `HubFixture` of a pi-family model: PaliGemma's tokenizer, then the checkpoint."""
    from vlaquantbench.hub.fixture import HubFixture

    return HubFixture(
        tokenizers={PALIGEMMA_TOKENIZER: write_released_tokenizer},
        write_checkpoint=lambda folder, seed: write_pi_checkpoint(folder, adapter_class, make_processors, normalization, seed),
    )
