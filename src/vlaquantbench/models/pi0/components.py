"""pi0 component scopes (paper `tab:vla_params`: VE 162, MP 1, LLM 126, AH 131 linear layers).

Unlike pi0.5, pi0's expert has plain RMSNorms (no adaRMS `dense`) and conditions on the robot
state through `state_proj` and on time through the fused action-time MLP.
"""

from lerobot.policies.pi0 import modeling_pi0
from lerobot.policies.pi0.configuration_pi0 import PI0Config

from vlaquantbench.models.paligemma_family import pi_builders, pi_components
from vlaquantbench.models.registry import ModelSpec

SPEC = ModelSpec(
    name="pi0",
    components=pi_components(
        ("action_in_proj", "action_out_proj", "state_proj", "action_time_mlp_in", "action_time_mlp_out")
    ),
    builders=pi_builders(modeling_pi0, modeling_pi0.PI0Pytorch, PI0Config),
)
