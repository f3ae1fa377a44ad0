"""OpenVLA-OFT component scopes (paper `tab:vla_params`: VE 209, MP 5, LLM 224, AH 4 linear layers).

MP holds both projectors (vision features and robot state into the LLM). VE counts SigLIP's
attention-pooling head too: the policy never runs it, which is why the paper observes 204 of the
209 VE layers during calibration and why hook accounting reports those 5 as unfired.

No residual stream is declared for the Hadamard rotation's offline form (`quant.rotation`): the
LLaMA's per-layer RMSNorms would fold, but its final norm's output feeds the action head's
LayerNorm over 7 concatenated hidden states, which subtracts their mean and so cannot read a
rotated stream; DINOv2 and SigLIP use LayerNorm. Every OFT input is rotated online.
"""

from vlaquantbench.models.openvla_oft.architecture import DEMO, OpenVLAOFT
from vlaquantbench.models.registry import Component, ModelSpec, demo_build, seeded_build

SPEC = ModelSpec(
    name="openvla_oft",
    components={
        "ve": Component(roots=("vision_backbone",)),
        "mp": Component(roots=("projector", "proprio_projector")),
        "llm": Component(roots=("language_model",), never=("language_model.lm_head",)),
        "ah": Component(roots=("action_head",)),
    },
    builders={"full": lambda device, seed: seeded_build(OpenVLAOFT, device, seed),
              "demo": lambda device, seed: demo_build(lambda: OpenVLAOFT(DEMO), device, seed)},
)
