"""OpenVLA-OFT adapter, driven like the OFT release's LIBERO client (`run_libero_eval.py`).

Observation -> the main and wrist cameras (by the roles their benchmark declares, `AdapterConfig.cameras`)
as the benchmark's env renders them (LIBERO's rotated 180 degrees, as the client flips them itself), each
resized to 224 px, center-cropped to 90% of its area and resized back (the client's `center_crop`),
normalized for DINOv2 (ImageNet statistics) and for SigLIP (mean 0.5, std 0.5) -> the 8-D state
normalized to [-1, 1] by the checkpoint's proprio q01/q99 -> the prompt "In: What action should the
robot take to <instruction>?\\nOut:" -> one parallel-decoding pass (`OpenVLAOFT.forward`) -> 8
actions in [-1, 1] unnormalized by the action q01/q99 on the masked dimensions -> the gripper mapped
from [0, 1] to -1/+1 (the client's `normalize_gripper_action(binarize=True)`) and its sign inverted where the
benchmark's adapter conventions say so (`client.ADAPTER_CONVENTIONS`; on LIBERO, the client's
`invert_gripper_action`). The L1 head is deterministic: nothing is sampled, and the model seed
is fixed at the client's 7. Prompts differ in length, so each observation runs as its own pass, as
in the client (one query per step): an episode's actions never depend on its batch.

Full variant: the local snapshot of `moojink/openvla-7b-oft-finetuned-libero-<suite>` as the release ships
it (`release`): its safetensors shards (vision backbone, projector, LLaMA-2), the
`proprio_projector--*_checkpoint.pt` and `action_head--*_checkpoint.pt` files, `dataset_statistics.json`
(key `<suite>_no_noops`) and its LLaMA tokenizer, each checked before any rollout, the weights loaded
strictly at the widths its config.json gives. Demo variant: the reduced-width random-weight build of
the model spec, the offline byte-level tokenizer and LIBERO-like ranges as statistics. Random: the
full-size build, seeded.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterBase
from vlaquantbench.models.openvla_oft.architecture import ACTION_DIM, CHUNK, IMAGE_SIZE
from vlaquantbench.models.openvla_oft.client import MODEL_SEED
from vlaquantbench.models.registry import get_model_spec

BOS, STOP = 1, 2  # LLaMA-2's <s> and </s>
CROP_AREA = 0.9
_DINO_MEAN, _DINO_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
_SIGLIP_MEAN, _SIGLIP_STD = (0.5, 0.5, 0.5), (0.5, 0.5, 0.5)


def prompt(instruction: str) -> str:
    return f"In: What action should the robot take to {instruction.lower()}?\nOut:"


def demo_statistics() -> dict:
    """LIBERO-like ranges (not dataset statistics) in `dataset_statistics.json`'s layout."""
    from vlaquantbench.models.pi_family_adapter import _STATE_HIGH, _STATE_LOW

    return {
        "action": {"q01": [-1.0] * 6 + [0.0], "q99": [1.0] * 6 + [1.0], "mask": [True] * 6 + [False]},
        "proprio": {"q01": _STATE_LOW, "q99": _STATE_HIGH},
    }


def _normalize(x: torch.Tensor, mean, std) -> torch.Tensor:
    return (x - torch.tensor(mean).view(1, 3, 1, 1)) / torch.tensor(std).view(1, 3, 1, 1)


class OpenVLAOFTAdapter(AdapterBase):
    name = "openvla_oft"
    calibrated_components = ("ve", "mp", "llm", "ah")
    # SigLIP's attention-pooling head: counted in VE (tab:vla_params, 209 layers) but never run, as
    # the policy reads patch features; the paper observes 204 of the 209 VE layers.
    idle_layers = ("vision_backbone.fused_featurizer.attn_pool.*",)


    def load(self) -> None:
        from vlaquantbench.models.pi_family_adapter import offline_byte_tokenizer

        torch.manual_seed(MODEL_SEED)  # the client's `set_seed_everywhere(7)`; the head samples nothing
        if self.config.variant == "full":
            self._load_checkpoint()
        elif self.config.variant in ("demo", "random"):
            build = "demo" if self.config.variant == "demo" else "full"
            self.model = get_model_spec(self.name).build(variant=build, device=self._device, seed=self.config.seed)
            self.model.to(getattr(torch, self.config.dtype))
            self.tokenizer = offline_byte_tokenizer()
            self.statistics = demo_statistics()
        else:
            raise UserError(f"openvla_oft has no variant {self.config.variant!r}; choose full, demo or random")
        self.model.eval()
        self.predicted_chunk = CHUNK
        self._check_chunk()

    def _load_checkpoint(self) -> None:
        """The release's snapshot (`release`), checked before any rollout (revision, config.json, the
        suite's statistics, the tokenizer, every weights file against the architecture's keys and
        shapes), then loaded strictly into the architecture built at config.json's widths."""
        from vlaquantbench.hub import checks
        from vlaquantbench.models.openvla_oft import release
        from vlaquantbench.models.openvla_oft.architecture import OpenVLAOFT

        folder = self.config.checkpoint_dir
        if not folder or not Path(folder).is_dir():
            raise UserError(f"openvla_oft: checkpoint {self.config.checkpoint} has no local snapshot; run its download rule")
        checks.check_snapshot_revision(folder, self.config.checkpoint, self.config.revision)
        sizes, reduced = release.read_sizes(folder)
        self.statistics, statistics_record = release.read_statistics(folder, self.config.suite)
        self.tokenizer, tokenizer_record = release.load_tokenizer(folder, self.config.checkpoint)
        with torch.device("meta"):
            model = OpenVLAOFT(sizes)
        expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
        model.load_state_dict(release.load_state(folder, expected, self.config.checkpoint), strict=True, assign=True)
        model.restore_rotary_embedding()  # a buffer no state dict holds, still on the meta device
        self.model = model.to(self._device, getattr(torch, self.config.dtype))
        self.checkpoint_provenance = {
            "tokenizer": tokenizer_record,
            "normalization": {"statistics": statistics_record},
            "widths": "reduced (offline hub fixture)" if reduced else "released",
        }

    def prepare_inference(self, report) -> dict:
        return {"sampler": "eager", "deterministic_head": True, "model_seed": MODEL_SEED}

    @torch.no_grad()
    def act(self, observations: Sequence[dict[str, Any]], generators: Sequence[torch.Generator]) -> np.ndarray:
        self._start_chunk(observations, generators)
        return np.stack([self._act_one(obs, self.adapter_conventions(obs)) for obs in observations])

    def _camera(self, obs: dict[str, Any], role: str) -> np.ndarray:
        pixels = self.camera_images([obs], role)
        if pixels is None:
            raise UserError(f"{self.name}: the observation (keys {sorted(obs)}) has no {role} camera "
                            f"(cameras {self.cameras(obs)}); the policy reads the main and wrist views")
        return pixels[0]

    def _act_one(self, obs: dict[str, Any], conventions) -> np.ndarray:
        dtype = next(self.model.parameters()).dtype
        views = torch.stack([self._image(self._camera(obs, role)) for role in ("main", "wrist")])
        dino = _normalize(views, _DINO_MEAN, _DINO_STD).to(self._device, dtype)
        siglip = _normalize(views, _SIGLIP_MEAN, _SIGLIP_STD).to(self._device, dtype)
        low, high = (np.asarray(self.statistics["proprio"][k], dtype=np.float64) for k in ("q01", "q99"))
        state = np.clip(2 * (obs["state"] - low) / np.maximum(high - low, 1e-8) - 1, -1, 1)
        proprio = torch.tensor(state, dtype=dtype, device=self._device).unsqueeze(0)
        ids = self.tokenizer(prompt(obs["instruction"]), add_special_tokens=False)["input_ids"]
        ids = torch.tensor([[BOS, *ids, STOP]], device=self._device)
        embeds = self.model.language_model.get_input_embeddings()(ids)
        normalized = self.model(dino, siglip, proprio, embeds)[0].float().cpu().numpy()  # [CHUNK, 7] in [-1, 1]
        return self._environment_actions(normalized, conventions)

    @staticmethod
    def _image(pixels: np.ndarray) -> torch.Tensor:
        """Resize to 224, center-crop 90% of the area, resize back; [3, 224, 224] in [0, 1]."""
        resize = torch.nn.functional.interpolate
        img = torch.from_numpy(np.ascontiguousarray(pixels)).permute(2, 0, 1).float().div(255.0).unsqueeze(0)
        img = resize(img, size=(IMAGE_SIZE, IMAGE_SIZE), mode="bilinear", align_corners=False, antialias=True)
        side = int(round(IMAGE_SIZE * CROP_AREA**0.5))
        start = (IMAGE_SIZE - side) // 2
        img = img[:, :, start : start + side, start : start + side]
        return resize(img, size=(IMAGE_SIZE, IMAGE_SIZE), mode="bilinear", align_corners=False, antialias=True)[0]

    def _environment_actions(self, normalized: np.ndarray, conventions) -> np.ndarray:
        stats = self.statistics["action"]
        low, high = np.asarray(stats["q01"]), np.asarray(stats["q99"])
        mask = np.asarray(stats.get("mask", [True] * ACTION_DIM), dtype=bool)
        actions = np.where(mask, 0.5 * (normalized + 1) * (high - low) + low, normalized)
        # Gripper: [0, 1] -> [-1, 1], binarized (the client's `normalize_gripper_action(binarize=True)`), then
        # inverted where the benchmark's env closes at the other end.
        gripper = np.sign(2 * actions[:, -1] - 1)
        actions[:, -1] = -gripper if conventions.gripper_inverted else gripper
        return actions.astype(np.float32)


ADAPTER = OpenVLAOFTAdapter
