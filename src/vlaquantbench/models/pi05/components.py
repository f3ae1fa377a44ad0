"""pi0.5 component scopes (paper `tab:vla_params`: VE 162, MP 1, LLM 126, AH 167 linear layers).

The action expert (AH) includes its adaRMS modulations (`*layernorm.dense`, the final
`gemma_expert.model.norm.dense`) and the flow-matching projections around it. Its adaptive RMSNorms
scale and shift each sample's channels by a modulation of the flow time, so no fixed gain folds
into the next layers: the expert declares no foldable residual stream and a Hadamard rotation
rotates its inputs online; the VLM's stream folds (`paligemma_family.vlm_stream`).
"""

from lerobot.policies.pi05 import modeling_pi05
from lerobot.policies.pi05.configuration_pi05 import PI05Config

from vlaquantbench.models.paligemma_family import pi_builders, pi_components
from vlaquantbench.models.registry import ModelSpec

SPEC = ModelSpec(
    name="pi05",
    components=pi_components(("action_in_proj", "action_out_proj", "time_mlp_in", "time_mlp_out")),
    builders=pi_builders(modeling_pi05, modeling_pi05.PI05Pytorch, PI05Config),
)
