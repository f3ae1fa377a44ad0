"""pi0 component scopes (paper `tab:vla_params`: VE 162, MP 1, LLM 126, AH 131 linear layers).

Unlike pi0.5, pi0's expert has plain RMSNorms (no adaRMS `dense`) and conditions on the robot
state through `state_proj` and on time through the fused action-time MLP.
"""

from lerobot.policies.pi0 import modeling_pi0
from lerobot.policies.pi0.configuration_pi0 import PI0Config

from vlaquantbench.models.paligemma_family import EXPERT_DECODER, gemma_stream, pi_builders, pi_components
from vlaquantbench.models.registry import ModelSpec


def expert_stream(model) -> tuple:
    """The expert's Gemma stream: written by the state token (`state_proj`) and the action-time
    tokens (`action_time_mlp_out`; `action_in_proj` feeds the MLP, not the stream); its final norm
    is read by `action_out_proj`, which takes that norm's gain."""
    return (gemma_stream(model, "expert", EXPERT_DECODER, ("state_proj", "action_time_mlp_out"),
                         final_readers=("action_out_proj",)),)


SPEC = ModelSpec(
    name="pi0",
    components=pi_components(
        ("action_in_proj", "action_out_proj", "state_proj", "action_time_mlp_in", "action_time_mlp_out"),
        expert_stream,
    ),
    builders=pi_builders(modeling_pi0, modeling_pi0.PI0Pytorch, PI0Config),
)
