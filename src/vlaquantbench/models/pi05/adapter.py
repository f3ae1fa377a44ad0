"""pi0.5 adapter (lerobot 0.6.1 `PI05Pytorch`): the state enters the prompt as 256-bin tokens."""

from __future__ import annotations

import numpy as np
import torch

from vlaquantbench.models.adapter import episode_generator, fast_path_probe, ulp_moved
from vlaquantbench.models.pi_family_adapter import PiFamilyAdapter


class Pi05Adapter(PiFamilyAdapter):
    name = "pi05"
    policy_module = "lerobot.policies.pi05"
    policy_class = "PI05Policy"
    config_class = "PI05Config"
    supports_captured_sampler = True
    _captured = None

    def _input_steps(self, steps, tokenize, policy_config) -> list:
        from lerobot.policies.pi05.processor_pi05 import Pi05PrepareStateTokenizerProcessorStep

        prompt_with_state = Pi05PrepareStateTokenizerProcessorStep(max_state_dim=policy_config.max_state_dim)
        # Normalize first: the prompt discretizes the normalized state into 256 bins.
        return [steps.rename_observations, steps.add_batch_dim, steps.normalize, prompt_with_state, tokenize, steps.to_device]

    def prepare_inference(self, report) -> dict:
        if self.config.sampler != "captured":
            return super().prepare_inference(report)
        from vlaquantbench.models.pi05.fast import CapturedSampler
        from vlaquantbench.models.pi05.fast.captured import REPLAY_COST_ROWS
        from vlaquantbench.quant import fused_kernel
        from vlaquantbench.quant.fused_kernel import fuse_activation_hooks

        # Fused per-token quantization is bit-identical to the hooks' own on CUDA; elsewhere it
        # would fall back to them, so it is only swapped in there.
        fused = (report is not None and self._device.type == "cuda" and fused_kernel.triton is not None
                 and fuse_activation_hooks(report) > 0)
        # Graphs are captured on first use, so after the hooks are in place.
        self._captured = CapturedSampler(self.model, num_steps=self.config.flow_steps)
        graphs = self._captured.use_graphs
        # With graphs a batch's rows run in the graphs of its plan, which sets their kernels' shapes
        # (a cell recorded under other plans is not resumed with these).
        plan = {"graph_plan": {"sizes": list(self._captured.graph_sizes), "replay_cost_rows": REPLAY_COST_ROWS}}
        return {"sampler": "captured", "cuda_graph": graphs, **(plan if graphs else {}), "fused_quant": fused,
                "tf32": graphs and self._captured.tf32}

    @torch.no_grad()
    def fast_path_probe(self) -> dict | None:
        """The captured sampler's first chunk against lerobot's eager `sample_actions` on one fixed
        observation (seeded random camera images keyed by role and state, an instruction, seed-0 noise),
        before any episode; the graphs it captured are dropped, so the episodes capture (and count
        their quantizers' runs) afresh."""
        if self.config.sampler != "captured":
            return None
        rng = np.random.default_rng(0)
        roles = {role: role for role in self._role_features()}  # the probe's observation is keyed by role
        observation = {role: rng.integers(0, 256, (224, 224, 3), dtype=np.uint8) for role in roles}
        observation |= {"state": rng.uniform(-0.05, 0.05, self.state_dim).astype(np.float32),
                        "instruction": "pick up the black bowl and place it on the plate"}
        batch = self.preprocessor(self._lerobot_batch([observation], roles))
        images, image_masks = self._images(batch)
        shape = (1, self.predicted_chunk, int(self.policy_config.max_action_dim))
        noise = torch.randn(shape, generator=episode_generator(0)).to(self._device)
        fast = self._sample(batch, images, image_masks, noise)
        tokens, masks = batch["observation.language.tokens"], batch["observation.language.attention_mask"]

        def eager_chunk(images, noise):
            return self.model.sample_actions(images, image_masks, tokens, masks, noise=noise.clone(),
                                             num_steps=self.config.flow_steps)

        def eager_ulp_moved(seed: int):  # the CPU bound's reference: see models.adapter.CPU_PROBE_FACTOR
            directions = torch.Generator().manual_seed(seed)
            return eager_chunk([ulp_moved(image, directions) for image in images], ulp_moved(noise, directions))

        eager = eager_chunk(images, noise)
        self._captured.reset()
        return fast_path_probe("captured", fast, eager, eager_ulp_moved)

    def _sample(self, batch, images, image_masks, noise):
        tokens, masks = batch["observation.language.tokens"], batch["observation.language.attention_mask"]
        if self.config.sampler == "captured":
            if self._captured is None:  # used without `prepare_inference`: no hooks to fuse
                self.prepare_inference(None)
            return self._captured(images, image_masks, tokens, masks, noise)
        return self.model.sample_actions(images, image_masks, tokens, masks, noise=noise, num_steps=self.config.flow_steps)


ADAPTER = Pi05Adapter
