"""X-VLA component scopes (paper `tab:vla_params`: VE 96, MP 0, LLM 72, AH 98 linear layers).

X-VLA runs the encoder side of Florence-2-large (DaViT vision tower, BART-large text encoder) and
a 24-block soft-prompted transformer as its action head. It has no separate MP scope: the released
checkpoint projects image features with a raw parameter matrix, not a linear layer, so the native
`multi_modal_projector.image_projection` that lerobot builds in its place belongs to no component.
The domain-aware action encoder/decoder are embedding lookups, not `nn.Linear`, so never selected.
"""

from lerobot.policies.xvla.configuration_xvla import XVLAConfig
from lerobot.policies.xvla.modeling_xvla import XVLAModel

from vlaquantbench.models.registry import Component, ModelSpec, seeded_build

# Florence-2-large as stored with `2toINF/X-VLA-Libero` (remote-code field names; lerobot translates).
FLORENCE_LARGE = {
    "vision_config": {
        "model_type": "davit",
        "dim_embed": [256, 512, 1024, 2048],
        "num_heads": [8, 16, 32, 64],
        "num_groups": [8, 16, 32, 64],
        "depths": [1, 1, 9, 1],
        "patch_size": [7, 3, 3, 3],
        "patch_stride": [4, 2, 2, 2],
        "patch_padding": [3, 1, 1, 1],
        "patch_prenorm": [False, True, True, True],
        "window_size": 12,
        "projection_dim": 1024,
    },
    "text_config": {
        "model_type": "florence2_language",
        "vocab_size": 51289,
        "d_model": 1024,
        "encoder_layers": 12,
        "decoder_layers": 12,
        "encoder_attention_heads": 16,
        "decoder_attention_heads": 16,
        "encoder_ffn_dim": 4096,
        "decoder_ffn_dim": 4096,
    },
}
PROPRIO_DIM = 20  # X-VLA-Libero's ee6d state: two 10-D end-effector poses


def _build(device, seed):
    config = XVLAConfig(florence_config=FLORENCE_LARGE, hidden_size=1024, depth=24, num_heads=16, device="cpu")
    florence = config.get_florence_config()
    return seeded_build(lambda: XVLAModel(config, florence, proprio_dim=PROPRIO_DIM), device, seed)


SPEC = ModelSpec(
    name="xvla",
    components={
        "ve": Component(roots=("vlm.vision_tower",)),
        "llm": Component(roots=("vlm.language_model.encoder",)),
        "ah": Component(roots=("transformer",)),
    },
    builders={"full": _build},
)
