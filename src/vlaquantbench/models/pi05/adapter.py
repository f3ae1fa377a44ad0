"""pi0.5 adapter (lerobot 0.6.1 `PI05Pytorch`): the state enters the prompt as 256-bin tokens."""

from __future__ import annotations

from vlaquantbench.models.pi_family_adapter import PiFamilyAdapter


class Pi05Adapter(PiFamilyAdapter):
    name = "pi05"
    policy_module = "lerobot.policies.pi05"
    policy_class = "PI05Policy"
    config_class = "PI05Config"

    def _input_steps(self, steps, tokenize, policy_config) -> list:
        from lerobot.policies.pi05.processor_pi05 import Pi05PrepareStateTokenizerProcessorStep

        prompt_with_state = Pi05PrepareStateTokenizerProcessorStep(max_state_dim=policy_config.max_state_dim)
        # Normalize first: the prompt discretizes the normalized state into 256 bins.
        return [steps.rename_observations, steps.add_batch_dim, steps.normalize, prompt_with_state, tokenize, steps.to_device]

    def _sample(self, batch, images, image_masks, noise):
        return self.model.sample_actions(
            images,
            image_masks,
            batch["observation.language.tokens"],
            batch["observation.language.attention_mask"],
            noise=noise,
            num_steps=self.config.flow_steps,
        )


ADAPTER = Pi05Adapter
