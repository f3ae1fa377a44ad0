"""pi0 adapter (lerobot 0.6.1 `PI0Pytorch`): the normalized state is a separate model input."""

from __future__ import annotations

from vlaquantbench.models.pi_family_adapter import DEMO_STATS, STATE_KEY, PiFamilyAdapter, offline_byte_tokenizer


class Pi0Adapter(PiFamilyAdapter):
    name = "pi0"
    policy_module = "lerobot.policies.pi0"
    policy_class = "PI0Policy"
    config_class = "PI0Config"

    def _demo_processors(self, policy_config):
        from lerobot.policies.pi0.processor_pi0 import Pi0NewLineProcessor
        from lerobot.processor import (
            TokenizerProcessorStep,
            make_default_policy_processor_steps,
            make_policy_processor_pipelines,
        )

        # lerobot's pi0 pipeline (`make_pi0_pre_post_processors`) with the offline tokenizer.
        steps = make_default_policy_processor_steps(policy_config, DEMO_STATS)
        input_steps = [
            steps.rename_observations,
            steps.add_batch_dim,
            Pi0NewLineProcessor(),
            TokenizerProcessorStep(
                tokenizer=offline_byte_tokenizer(),
                max_length=policy_config.tokenizer_max_length,
                padding_side="right",
                padding="max_length",
            ),
            steps.to_device,
            steps.normalize,
        ]
        return make_policy_processor_pipelines(input_steps, [steps.unnormalize, steps.to_cpu])

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
