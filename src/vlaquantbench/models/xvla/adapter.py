"""X-VLA adapter (lerobot 0.6.1 `XVLAModel`), driven like X-VLA's released LIBERO client.

Observation -> the main camera (by the role its benchmark declares, `AdapterConfig.cameras`) as the env
renders it (LIBERO's rotated 180 degrees), the wrist camera turned back where the benchmark's adapter conventions
say so (`client.ADAPTER_CONVENTIONS`: on LIBERO the client flips only the primary view, while the environment
rotates both), each resized to 224 px and ImageNet-normalized -> the proprio vector: end-effector position, the
first two columns of its rotation matrix (6-D rotation), a zero, then ten zeros (the client's 20-D ee6d layout)
-> the instruction tokenized to 64 tokens -> the benchmark's domain id (its conventions'; LIBERO's 3) -> flow
matching over `flow_steps` steps from noise drawn from each episode's own generator -> per action: absolute
target position, the 6-D rotation as axis-angle, the gripper thresholded at 0.5 to +1/-1. The environment runs its controller with absolute targets
(`control_mode = "absolute"`) and the whole 30-action chunk is executed before the next query.

Full variant: the local snapshot of `2toINF/X-VLA-Libero` as the release ships it (`release`):
lerobot's `XVLAModel` built from its config.json, its weights through lerobot's remap of the
remote-code Florence-2 layout, its own BART tokenizer and its image processor's size, resampling,
mean and std, each checked before any rollout. Demo variant: the reduced-width random-weight model of
the model spec, an offline byte-level tokenizer (see `pi_family_adapter.offline_byte_tokenizer`) and
the release's image settings as constants. Random variant: the full-size architecture, seeded.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterBase, BatchInvariantLinears
from vlaquantbench.models.registry import get_model_spec
from vlaquantbench.quant.steps import attach_flow_clock, flow_clock

TOKENS = 64  # lerobot's `tokenizer_max_length` for X-VLA
# The demo's image settings: the release's 224 px and ImageNet mean/std (its preprocessor_config.json);
# bilinear resizing, as the demo cells have always run (the release resizes bicubic).
DEMO_IMAGE = {"size": 224, "mode": "bilinear", "mean": [0.485, 0.456, 0.406], "std": [0.229, 0.224, 0.225]}


def axis_angle_to_rotate6d(axis_angle: np.ndarray) -> np.ndarray:
    """[n, 3] axis-angle -> [n, 6]: the first two columns of the rotation matrix."""
    from scipy.spatial.transform import Rotation

    matrices = Rotation.from_rotvec(axis_angle).as_matrix()
    return np.concatenate([matrices[:, :, 0], matrices[:, :, 1]], axis=-1)


def rotate6d_to_axis_angle(r6d: np.ndarray) -> np.ndarray:
    """[n, 6] -> [n, 3]: Gram-Schmidt on the two columns, the third by cross product, as axis-angle."""
    from scipy.spatial.transform import Rotation

    a1, a2 = r6d[:, :3], r6d[:, 3:6]
    b1 = a1 / (np.linalg.norm(a1, axis=-1, keepdims=True) + 1e-6)
    b2 = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    b2 = b2 / (np.linalg.norm(b2, axis=-1, keepdims=True) + 1e-6)
    matrices = np.stack([b1, b2, np.cross(b1, b2)], axis=-1)
    return Rotation.from_matrix(matrices).as_rotvec()


class XVLAAdapter(AdapterBase):
    name = "xvla"
    calibrated_components = ("ve", "llm", "ah")  # X-VLA has no MP scope
    control_mode = "absolute"  # actions are absolute end-effector targets


    def load(self) -> None:
        from vlaquantbench.models.pi_family_adapter import DEMO_PROVENANCE, offline_byte_tokenizer

        spec = get_model_spec(self.name)
        self._image = DEMO_IMAGE
        if self.config.variant == "full":
            self._load_checkpoint()
        elif self.config.variant in ("demo", "random"):
            self.checkpoint_provenance = {"tokenizer": DEMO_PROVENANCE["tokenizer"],
                                          "normalization": {"image": DEMO_IMAGE, "source": "X-VLA's image settings"},
                                          "widths": "reduced (demo)" if self.config.variant == "demo" else "released"}
            if self.config.variant == "random" and self.config.dtype not in ("float32", "bfloat16"):
                raise UserError(f"xvla: variant 'random' runs in float32 or bfloat16, not {self.config.dtype!r}")
            build = "demo" if self.config.variant == "demo" else "full"
            self.model = spec.build(variant=build, device=self._device, seed=self.config.seed)
            if self.config.variant == "random" and self.config.dtype == "bfloat16":
                self.model.to(torch.bfloat16)
            self.tokenizer = offline_byte_tokenizer()
        else:
            raise UserError(f"xvla has no variant {self.config.variant!r}; choose full, demo or random")
        self.model.eval()
        attach_flow_clock(self.model)  # advanced by `act`'s flow loop (`quant.steps`)
        eager_cpu = self._device.type == "cpu" and self.config.sampler == "eager"
        self._invariance = BatchInvariantLinears(self.model) if eager_cpu else None
        self.predicted_chunk = int(self.model.chunk_size)
        self._check_chunk()

    def _load_checkpoint(self) -> None:
        """The release's snapshot, checked before any rollout (revision, config, image processor,
        tokenizer, a state dict that fits the architecture), then loaded strictly."""
        from safetensors.torch import load_file

        from vlaquantbench.hub import checks
        from vlaquantbench.models.xvla import release
        from vlaquantbench.models.xvla.components import FLORENCE_LARGE, FULL_HEAD

        folder = self.config.checkpoint_dir
        if not folder:
            raise UserError(f"xvla: checkpoint {self.config.checkpoint} has no local snapshot; run its download rule")
        checks.check_snapshot_revision(folder, self.config.checkpoint, self.config.revision)
        released = release.read_config(folder)
        self._image, image_record = release.read_image_processor(folder)
        self.tokenizer, tokenizer_record = release.load_tokenizer(folder, self.config.checkpoint)
        weights = Path(folder) / release.WEIGHTS_FILE
        found = {k: torch.empty(shape, device="meta") for k, shape in checks.weight_shapes(weights).items()}
        policy_config = release.policy_config(released, self.config.device, self.config.dtype)
        expected = release.build_model(policy_config, device="meta").state_dict()
        checks.check_state_dict_fits({k: tuple(v.shape) for k, v in release.lerobot_state(found).items()},
                                     {k: tuple(v.shape) for k, v in expected.items()}, weights)
        model = release.build_model(policy_config)
        model.load_state_dict(release.lerobot_state(load_file(weights)), strict=True)
        model._apply_dtype()  # lerobot's cast to the configured dtype, as after its own from_pretrained
        self.model = model.to(self._device)
        full = released["florence_config"]["text_config"].get("d_model") == FLORENCE_LARGE["text_config"]["d_model"]
        self.checkpoint_provenance = {
            "tokenizer": tokenizer_record,
            "normalization": {"image_processor": image_record},
            "widths": "released" if full and released["hidden_size"] == FULL_HEAD["hidden_size"] else "reduced (config.json)",
        }

    @torch.no_grad()
    def act(self, observations: Sequence[dict[str, Any]], generators: Sequence[torch.Generator]) -> np.ndarray:
        self._start_chunk(observations, generators)
        model, n = self.model, len(observations)
        dtype = next(model.parameters()).dtype
        conventions = self.adapter_conventions(observations[0])
        images = torch.stack([self._view(observations, "main", conventions),
                              self._view(observations, "wrist", conventions)], dim=1)
        mask = torch.ones(n, 2, dtype=torch.bool, device=self._device)
        tokens = self.tokenizer([obs["instruction"] for obs in observations], max_length=TOKENS,
                                padding="max_length", truncation=True, return_tensors="pt")["input_ids"]
        proprio = torch.from_numpy(self._proprio(observations)).to(self._device, dtype)
        domain = torch.full((n,), conventions.domain_id, dtype=torch.long, device=self._device)
        enc = model.forward_vlm(tokens.to(self._device), images.to(dtype), mask)
        # `XVLAModel.generate_actions`, with the starting noise from each episode's own stream.
        shape = (self.predicted_chunk, model.dim_action)
        noise = torch.stack([torch.randn(shape, generator=g) for g in generators]).to(self._device, dtype)
        action = torch.zeros_like(noise)
        steps = max(1, int(self.config.flow_steps))
        clock = flow_clock(model)
        with clock.chunk():
            for i in range(steps, 0, -1):
                t = torch.full((n,), i / steps, device=self._device, dtype=dtype)
                x_t = noise * t.view(-1, 1, 1) + action * (1 - t).view(-1, 1, 1)
                proprio_m, x_t_m = model.action_space.preprocess(proprio, x_t)
                with clock.flow_step():
                    action = model.transformer(domain_id=domain, action_with_noise=x_t_m, proprio=proprio_m, t=t, **enc)
        return self._environment_actions(model.action_space.postprocess(action).float().cpu().numpy())

    def _view(self, observations, role: str, conventions) -> torch.Tensor:
        pixels = self.camera_images(observations, role)  # n x H x W x 3, as the env renders it
        if pixels is None:
            raise UserError(f"{self.name}: the observation (keys {sorted(observations[0])}) has no {role} camera "
                            f"(cameras {self.cameras(observations[0])}); the policy reads the main and wrist views")
        if role == "wrist" and conventions.wrist_turned_back:
            pixels = pixels[:, ::-1, ::-1]
        img = torch.from_numpy(np.ascontiguousarray(pixels)).permute(0, 3, 1, 2).float().div(255.0).to(self._device)
        size = self._image["size"]
        if tuple(img.shape[2:]) != (size, size):
            img = torch.nn.functional.interpolate(img, size=(size, size), mode=self._image["mode"], align_corners=False)
        mean, std = (torch.tensor(self._image[k], device=img.device).view(1, 3, 1, 1) for k in ("mean", "std"))
        return (img - mean) / std

    def _proprio(self, observations) -> np.ndarray:
        state = np.stack([obs["state"] for obs in observations]).astype(np.float64)  # pos, axis-angle, gripper qpos
        pose = np.concatenate([state[:, :3], axis_angle_to_rotate6d(state[:, 3:6]), np.zeros((len(state), 1))], axis=-1)
        return np.concatenate([pose, np.zeros_like(pose)], axis=-1).astype(np.float32)

    @staticmethod
    def _environment_actions(actions: np.ndarray) -> np.ndarray:
        """[n, chunk, 20] ee6d -> [n, chunk, 7]: target position, axis-angle, gripper +1/-1."""
        n, chunk, _ = actions.shape
        flat = actions.reshape(n * chunk, -1)
        rotation = rotate6d_to_axis_angle(flat[:, 3:9].astype(np.float64))
        gripper = np.where(flat[:, 9:10] > 0.5, 1.0, -1.0)
        return np.concatenate([flat[:, :3], rotation, gripper], axis=-1).reshape(n, chunk, 7).astype(np.float32)


ADAPTER = XVLAAdapter
