"""pi0 adapter (lerobot 0.6.1 `PI0Pytorch`): the normalized state is a separate model input."""

from __future__ import annotations

from vlaquantbench.models.pi_family_adapter import STATE_KEY, PiFamilyAdapter


class Pi0Adapter(PiFamilyAdapter):
    name = "pi0"
    policy_module = "lerobot.policies.pi0"
    policy_class = "PI0Policy"
    config_class = "PI0Config"

    def _input_steps(self, steps, tokenize, policy_config) -> list:
        from lerobot.policies.pi0.processor_pi0 import Pi0NewLineProcessor

        return [steps.rename_observations, steps.add_batch_dim, Pi0NewLineProcessor(), tokenize, steps.to_device, steps.normalize]

    def _sample(self, batch, images, image_masks, noise):
        from lerobot.policies.common.vla_utils import pad_vector

        state = pad_vector(batch[STATE_KEY], self.policy_config.max_state_dim)
        return self.model.sample_actions(
            images,
            image_masks,
            batch["observation.language.tokens"],
            batch["observation.language.attention_mask"],
            state,
            noise=noise,
            num_steps=self.config.flow_steps,
        )


ADAPTER = Pi0Adapter
