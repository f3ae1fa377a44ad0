"""pi0.5 adapter (lerobot 0.6.1 `PI05Pytorch`): the state enters the prompt as 256-bin tokens."""

from __future__ import annotations

from vlaquantbench.models.pi_family_adapter import DEMO_STATS, PiFamilyAdapter, offline_byte_tokenizer


class Pi05Adapter(PiFamilyAdapter):
    name = "pi05"
    policy_module = "lerobot.policies.pi05"
    policy_class = "PI05Policy"
    config_class = "PI05Config"

    def _demo_processors(self, policy_config):
        from lerobot.policies.pi05.processor_pi05 import Pi05PrepareStateTokenizerProcessorStep
        from lerobot.processor import (
            TokenizerProcessorStep,
            make_default_policy_processor_steps,
            make_policy_processor_pipelines,
        )

        # lerobot's pi0.5 pipeline (`make_pi05_pre_post_processors`) with the offline tokenizer.
        steps = make_default_policy_processor_steps(policy_config, DEMO_STATS)
        input_steps = [
            steps.rename_observations,
            steps.add_batch_dim,
            steps.normalize,
            Pi05PrepareStateTokenizerProcessorStep(max_state_dim=policy_config.max_state_dim),
            TokenizerProcessorStep(
                tokenizer=offline_byte_tokenizer(),
                max_length=policy_config.tokenizer_max_length,
                padding_side="right",
                padding="max_length",
            ),
            steps.to_device,
        ]
        return make_policy_processor_pipelines(input_steps, [steps.unnormalize, steps.to_cpu])

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
