"""What the pi0 and pi0.5 adapters share: lerobot 0.6.1 policies driven like lerobot's evaluation
(camera images, state, instruction), with the flow noise drawn per episode.

Observation -> lerobot batch (each camera, found by the role its benchmark declares (`AdapterConfig.cameras`),
under the feature lerobot's datasets give that role, `ROLE_FEATURES`: the main view as `observation.images.image`
in two-camera datasets or `observation.image` in one-camera ones, the wrist view as `observation.images.image2`,
each as the environment renders it; `observation.state`; `task`) -> the
policy's preprocessor pipeline (normalization, tokenization) -> images resized with padding to the
model's resolution and mapped to [-1, 1] -> `sample_actions` with noise from each episode's
generator -> the checkpoint's action dimensions (its config's `action` feature) -> the
postprocessor (unnormalization). The cameras and the state size are those the checkpoint's config
declares; an observation lacking them is refused naming the features.

Full variant: `PI0xPolicy.from_pretrained` and the checkpoint's own processor files (the real
PaliGemma tokenizer). Demo variant: the reduced-width random-weight model of the model spec, and
lerobot's processor steps with fixed normalization ranges (`DEMO_STATS`) and an offline byte-level
tokenizer (the PaliGemma tokenizer cannot be fetched offline; a random-weight policy has no
vocabulary to match, so this changes nothing it could have learned). Random variant: the released
architecture at full size (the model spec's "full" build) with seeded random weights, in
lerobot's precision layout for `dtype` (bfloat16 with the vision path kept in float32, or all
float32), and the demo processors: what throughput benchmarks need when no checkpoint can load.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterBase, BatchInvariantLinears, wait_for_device
from vlaquantbench.models.paligemma_family import REDUCED_WIDTHS_FILE, TRAINING_FILE, checkpoint_widths
from vlaquantbench.models.registry import get_model_spec
from vlaquantbench.quant.steps import attach_flow_clock

# Camera role (`envs.registry.CAMERA_ROLES`) -> the lerobot features that role's image feeds, the first the
# checkpoint declares: the names lerobot's two-camera datasets (`image`, `image2`) and one-camera datasets
# (`observation.image`) give the main and wrist views.
ROLE_FEATURES = {"main": ("observation.images.image", "observation.image"), "wrist": ("observation.images.image2",)}
STATE_KEY = "observation.state"
# The demo and random variants' features: the released finetunes' (two cameras, 8-D state, 7-D actions).
ACTION_DIM = 7
STATE_DIM = 8

# Demo normalization ranges (not dataset statistics): the released finetunes' end-effector position (m), axis-angle
# (rad), gripper finger positions (m); actions are already in [-1, 1].
_STATE_LOW = [-0.4, -0.4, 0.8, -3.2, -3.2, -3.2, -0.05, -0.05]
_STATE_HIGH = [0.4, 0.4, 1.4, 3.2, 3.2, 3.2, 0.05, 0.05]


def _range_stats(low: list[float], high: list[float]) -> dict[str, torch.Tensor]:
    lo, hi = torch.tensor(low), torch.tensor(high)
    return {"min": lo, "max": hi, "q01": lo, "q99": hi, "mean": (lo + hi) / 2, "std": (hi - lo) / 4}


DEMO_STATS = {
    STATE_KEY: _range_stats(_STATE_LOW, _STATE_HIGH),
    "action": _range_stats([-1.0] * ACTION_DIM, [1.0] * ACTION_DIM),
}


# What the header of a random-weight (demo, random) cell records instead of a checkpoint's tokenizer
# and statistics: these stand-ins are never used for a released checkpoint.
DEMO_PROVENANCE = {
    "tokenizer": {"class": "PreTrainedTokenizerFast", "source": "offline_byte_tokenizer (random-weight policy only)"},
    "normalization": {"source": "DEMO_STATS fixed ranges (random-weight policy only)"},
}


def offline_byte_tokenizer():
    """A deterministic byte-level tokenizer built in code (no download): one token per UTF-8 byte."""
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast

    alphabet = pre_tokenizers.ByteLevel.alphabet()
    vocab = {"<pad>": 0, "<unk>": 1, **{ch: i + 2 for i, ch in enumerate(sorted(alphabet))}}
    tokenizer = Tokenizer(models.BPE(vocab=vocab, merges=[], unk_token="<unk>"))
    tokenizer.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False)
    tokenizer.decoder = decoders.ByteLevel()
    return PreTrainedTokenizerFast(tokenizer_object=tokenizer, pad_token="<pad>", unk_token="<unk>")


class PiFamilyAdapter(AdapterBase):
    """Base of the pi0/pi0.5 adapters; subclasses name the lerobot classes and the model call."""

    name: str
    policy_module: str  # e.g. "lerobot.policies.pi05"
    policy_class: str  # e.g. "PI05Policy"
    config_class: str  # e.g. "PI05Config"
    # Rollout calibration smooths VE, LLM and AH; both pi models leave the one-layer MP uncalibrated.
    calibrated_components = ("ve", "llm", "ah")


    # -- loading ---------------------------------------------------------------------------
    def load(self) -> None:
        if self.config.variant == "demo":
            self.model = get_model_spec(self.name).build(variant="demo", device=self._device, seed=self.config.seed)
            self.policy_config = self._demo_policy_config("float32")
            self.preprocessor, self.postprocessor = self._demo_processors(self.policy_config)
            self.checkpoint_provenance = {**DEMO_PROVENANCE, "widths": "reduced (demo)"}
        elif self.config.variant == "random":
            self.model = self._random_full_model()
            self.policy_config = self._demo_policy_config(self.config.dtype)
            self.preprocessor, self.postprocessor = self._demo_processors(self.policy_config)
            self.checkpoint_provenance = {**DEMO_PROVENANCE, "widths": "released"}
        else:
            self._load_checkpoint()
        self.model.eval()
        # Per-step calibration statistics and scales (`quant.steps`): a chunk per `sample_actions`
        # call, a flow step per `denoise_step` call (the captured sampler calls neither, and runs no
        # method that reads the clock: `MethodConfig.uncapturable`).
        attach_flow_clock(self.model, "sample_actions", "denoise_step")
        # Eager CPU float32 runs promise bit-identical actions at any batch size (see BatchInvariantLinears).
        eager_cpu = self._device.type == "cpu" and self.config.sampler == "eager"
        self._invariance = BatchInvariantLinears(self.model) if eager_cpu else None
        self.predicted_chunk = int(self.policy_config.chunk_size)
        self.image_keys = list(self.policy_config.image_features)
        self.state_dim = int(self.policy_config.input_features[STATE_KEY].shape[0])
        self.action_dim = int(self.policy_config.output_features["action"].shape[0])
        self._check_chunk()

    def _load_checkpoint(self) -> None:
        """The released checkpoint through lerobot's own loaders, after the checks lerobot's loaders
        skip (`vlaquantbench.hub.checks`): pinned revision, processor and normalizer files, tokenizer,
        and a state dict that fits the architecture."""
        from lerobot.policies.factory import make_pre_post_processors

        from vlaquantbench.hub import checks

        folder = self.config.checkpoint_dir
        if not folder:
            raise UserError(f"{self.name}: checkpoint {self.config.checkpoint} has no local snapshot; run its download rule")
        overrides: dict[str, dict] = {"device_processor": {"device": self.config.device}}
        if (Path(folder) / TRAINING_FILE).exists():  # trained here: a plain folder beside its tokenizer's
            tokenizer, provenance = self._trained_tokenizer(Path(folder))
            overrides["tokenizer_processor"] = {"tokenizer": tokenizer}  # instead of loading it by name
            tokenizers = [provenance]
            normalization = checks.check_processors(folder)
        else:
            checks.check_snapshot_revision(folder, self.config.checkpoint, self.config.revision)
            normalization = checks.check_processors(folder)
            tokenizers = [checks.load_tokenizer(name)[1] for name in checks.tokenizer_names(folder)]
        weights = Path(folder) / "model.safetensors"
        found = checks.weight_shapes(weights)
        lib = importlib.import_module(self.policy_module)
        policy_cls = getattr(lib, self.policy_class)
        policy_config = getattr(lib, self.config_class).from_pretrained(folder, local_files_only=True)
        policy_config.device = self.config.device  # the checkpoint's saved device may not exist here
        policy_config.dtype = self.config.dtype
        with checkpoint_widths(importlib.import_module(policy_cls.__module__), folder):
            policy = policy_cls.from_pretrained(folder, config=policy_config, local_files_only=True)
        checks.check_state_dict_fits(
            self._loaded_keys(policy, found), {k: tuple(v.shape) for k, v in policy.state_dict().items()}, weights
        )
        self.policy_config = policy.config
        self.model = policy.model.to(self._device)
        # lerobot's loader of a checkpoint's processors (as lerobot-eval uses it): the batch and
        # action converters, the relative/absolute action steps wired together.
        self.preprocessor, self.postprocessor = make_pre_post_processors(
            policy.config, pretrained_path=folder, preprocessor_overrides=overrides)
        self.checkpoint_provenance = {
            "tokenizer": tokenizers[0] if len(tokenizers) == 1 else tokenizers,
            "normalization": normalization,
            **self._widths_provenance(Path(folder)),
        }

    def _trained_tokenizer(self, folder: Path):
        """The task tokenizer of a checkpoint trained here, from its folder's tokenizer folder, after the
        folder is verified against its training.json (`trained_home.verify`: the weights against the
        revision the cell pins, every file against its SHA-256); and its provenance."""
        from transformers import AutoTokenizer

        from vlaquantbench.hub import checks
        from vlaquantbench.models import trained_home

        training = trained_home.verify(folder.parent, f"checkpoint {self.config.checkpoint}")
        if training["revision"] != self.config.revision:
            raise UserError(f"checkpoint {self.config.checkpoint}: {folder.parent} holds revision {training['revision']}, "
                            f"but the cell pins {self.config.revision}: run the cell's checkpoint rule again")
        recorded = training["tokenizer"]
        tokenizer, provenance = checks.load_snapshot_tokenizer(
            AutoTokenizer, trained_home.tokenizer_folder(folder.parent), recorded["repo"], checks.TOKENIZER_FILES)
        return tokenizer, {**provenance, "revision": recorded["revision"]}

    @staticmethod
    def _widths_provenance(folder: Path) -> dict:
        """The header's `widths` and, for a policy trained here, its `training` record (what it was
        trained on and how long; the whole record's sha256)."""
        if (folder / TRAINING_FILE).exists():
            from vlaquantbench.hub.checks import load_json, sha256

            record = load_json(folder / TRAINING_FILE, "training provenance")
            return {"widths": "reduced (trained here)",
                    "training": {"file": TRAINING_FILE, "sha256": sha256(folder / TRAINING_FILE),
                                 "dataset_manifest_sha256": record["dataset"]["manifest_sha256"],
                                 "steps": record["steps"], "batch_size": record["batch_size"],
                                 # a run ended before its planned steps says where and why
                                 **({"stopped_early": record["stopped_early"]} if "stopped_early" in record else {})}}
        return {"widths": "reduced (offline hub fixture)" if (folder / REDUCED_WIDTHS_FILE).exists() else "released"}

    @staticmethod
    def _loaded_keys(policy, shapes: dict[str, tuple]) -> dict[str, tuple]:
        """The file's keys and shapes as lerobot's `from_pretrained` renames them before loading
        (its key fixes, then the `model.` prefix), computed on meta tensors."""
        meta = {k: torch.empty(shape, device="meta") for k, shape in shapes.items()}
        fixed = policy._fix_pytorch_state_dict_keys(meta, policy.config)
        return {(k if k.startswith("model.") else f"model.{k}"): tuple(v.shape) for k, v in fixed.items()}

    def _random_full_model(self) -> nn.Module:
        if self.config.dtype not in ("bfloat16", "float32"):
            raise UserError(f"{self.name}: variant 'random' runs in bfloat16 or float32, not {self.config.dtype!r}")
        # The full build casts like lerobot's bfloat16 policy; float32 undoes it the way lerobot does.
        model = get_model_spec(self.name).build(variant="full", device=self._device, seed=self.config.seed)
        if self.config.dtype == "float32":
            model.paligemma_with_expert.to_bfloat16_for_selected_params("float32")
        return model

    def _demo_policy_config(self, dtype: str):
        from lerobot.configs import FeatureType, PolicyFeature

        lib = importlib.import_module(self.policy_module)
        config_cls = getattr(lib, self.config_class)
        image = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 224, 224))
        return config_cls(
            device=self.config.device,
            dtype=dtype,
            input_features={
                **{features[0]: image for features in ROLE_FEATURES.values()},
                STATE_KEY: PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
            },
            output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,))},
        )

    def _demo_processors(self, policy_config):
        """lerobot's processor pipelines for this policy, with demo statistics and the offline tokenizer."""
        from lerobot.processor import (
            TokenizerProcessorStep,
            make_default_policy_processor_steps,
            make_policy_processor_pipelines,
        )

        steps = make_default_policy_processor_steps(policy_config, DEMO_STATS)
        tokenize = TokenizerProcessorStep(
            tokenizer=offline_byte_tokenizer(),
            max_length=policy_config.tokenizer_max_length,
            padding_side="right",
            padding="max_length",
        )
        input_steps = self._input_steps(steps, tokenize, policy_config)
        return make_policy_processor_pipelines(input_steps, [steps.unnormalize, steps.to_cpu])

    def _input_steps(self, steps, tokenize, policy_config) -> list:
        """The policy's preprocessing steps in lerobot's order (`make_<policy>_pre_post_processors`)."""
        raise NotImplementedError

    # -- episodes --------------------------------------------------------------------------
    @torch.no_grad()
    def act(self, observations: Sequence[dict[str, Any]], generators: Sequence[torch.Generator]) -> np.ndarray:
        self._start_chunk(observations, generators)
        batch = self.preprocessor(self._lerobot_batch(observations))
        images, image_masks = self._images(batch)
        shape = (self.predicted_chunk, int(self.policy_config.max_action_dim))
        # Drawn on the CPU from each episode's own stream, then moved: identical on every device.
        noise = torch.stack([torch.randn(shape, generator=g) for g in generators]).to(self._device)
        actions = self._sample(batch, images, image_masks, noise)[:, :, :self.action_dim]
        wait_for_device(self._device)
        actions = self.postprocessor(actions.float())
        return actions.float().cpu().numpy()

    def _role_features(self) -> dict[str, str]:
        """Camera role -> the checkpoint's feature it feeds, for the roles the checkpoint reads."""
        return {role: feature for role, features in ROLE_FEATURES.items()
                for feature in [next((f for f in features if f in self.image_keys), None)] if feature is not None}

    def _lerobot_batch(self, observations: Sequence[dict[str, Any]],
                       cameras: dict[str, str] | None = None) -> dict[str, Any]:
        batch: dict[str, Any] = {}
        for role, feature in self._role_features().items():
            pixels = self.camera_images(observations, role, cameras)  # n x H x W x 3, uint8
            if pixels is None:
                continue
            # The uint8 pixels travel (a quarter of float32's bytes) and are widened where the policy
            # runs: on a GPU the closed-loop runner's main process, which shares the CPU with the
            # simulator workers, does no per-pixel work (division is exact-rounded on both devices).
            pixels = torch.from_numpy(pixels).to(self._device)
            batch[feature] = pixels.permute(0, 3, 1, 2).float().div(255.0)
        if not batch:
            raise UserError(f"{self.name}: the observation's cameras {cameras or self.cameras(observations[0])} "
                            f"(keys {sorted(observations[0])}) feed none of the checkpoint's cameras {self.image_keys} "
                            f"(role -> features: {ROLE_FEATURES})")
        state = np.stack([obs["state"] for obs in observations]).astype(np.float32)
        if state.shape[1] != self.state_dim:
            raise UserError(f"{self.name}: the observation's state has {state.shape[1]} dimensions; the checkpoint's "
                            f"{STATE_KEY} has {self.state_dim}")
        batch[STATE_KEY] = torch.from_numpy(state)
        batch["task"] = [obs["instruction"] for obs in observations]
        return batch

    def _images(self, batch: dict[str, Any]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Like lerobot's `_preprocess_images`: resize with padding, [0, 1] -> [-1, 1]; cameras the
        checkpoint expects but the environment lacks become masked constant images."""
        from lerobot.policies.common.vla_utils import resize_with_pad_torch

        height, width = self.policy_config.image_resolution
        images, masks = [], []
        present = [k for k in self.image_keys if k in batch]
        if not present:
            raise UserError(f"{self.name}: none of the checkpoint's cameras {self.image_keys} is delivered by the environment")
        n = batch[present[0]].shape[0]
        for key in self.image_keys:
            if key in batch:
                img = batch[key].to(self._device, torch.float32).permute(0, 2, 3, 1)
                if tuple(img.shape[1:3]) != (height, width):
                    img = resize_with_pad_torch(img, height, width)
                images.append((img * 2.0 - 1.0).permute(0, 3, 1, 2))
                masks.append(torch.ones(n, dtype=torch.bool, device=self._device))
            else:
                images.append(torch.full((n, 3, height, width), -1.0, device=self._device))
                masks.append(torch.zeros(n, dtype=torch.bool, device=self._device))
        return images, masks

    def _sample(self, batch, images, image_masks, noise) -> torch.Tensor:
        raise NotImplementedError
