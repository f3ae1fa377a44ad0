"""X-VLA component scopes (paper `tab:vla_params`: VE 96, MP 0, LLM 72, AH 98 linear layers).

X-VLA runs the encoder side of Florence-2-large (DaViT vision tower, BART-large text encoder) and
a 24-block soft-prompted transformer as its action head. It has no separate MP scope: the released
checkpoint projects image features with a raw parameter matrix, not a linear layer, so the native
`multi_modal_projector.image_projection` that lerobot builds in its place belongs to no component.
The domain-aware action encoder/decoder are embedding lookups, not `nn.Linear`, so never selected.
Every norm (DaViT, BART, the head) is a LayerNorm, whose mean subtraction and bias do not commute
with a rotation: no residual stream is declared foldable, and a Hadamard rotation rotates every
input online (`quant.transforms.Hadamard`).

The demo build keeps every depth (DaViT stages 1/1/9/1, 12 encoder layers, 24 head blocks), the
window size and the patch layout, so layer names and subset counts equal the full model's; only
widths and head counts shrink.
"""

import copy

from lerobot.policies.xvla.configuration_xvla import XVLAConfig
from lerobot.policies.xvla.modeling_xvla import XVLAModel

from vlaquantbench.models.registry import Component, ModelSpec, demo_build, seeded_build

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
CHUNK = 30  # X-VLA-Libero predicts 30 actions (`num_actions` of the release)
FULL_HEAD = dict(hidden_size=1024, depth=24, num_heads=16)


def _demo_florence() -> dict:
    florence = copy.deepcopy(FLORENCE_LARGE)
    florence["vision_config"].update(dim_embed=[16, 32, 64, 128], num_heads=[1, 2, 4, 8], num_groups=[1, 2, 4, 8],
                                     projection_dim=64)
    florence["text_config"].update(d_model=64, encoder_attention_heads=4, decoder_attention_heads=4,
                                   encoder_ffn_dim=128, decoder_ffn_dim=128)
    return florence


DEMO_FLORENCE = _demo_florence()
DEMO_HEAD = dict(hidden_size=64, depth=24, num_heads=4)


def policy_config(florence: dict, head: dict, **fields) -> XVLAConfig:
    """lerobot's X-VLA config with X-VLA-Libero's chunk, executed whole as its client does."""
    return XVLAConfig(florence_config=florence, chunk_size=CHUNK, n_action_steps=CHUNK, **head, **fields)


def _constructor(config: XVLAConfig):
    florence = config.get_florence_config()
    return lambda: XVLAModel(config, florence, proprio_dim=PROPRIO_DIM)


def _full(device, seed):
    return seeded_build(_constructor(policy_config(FLORENCE_LARGE, FULL_HEAD, device="cpu")), device, seed)


def _demo(device, seed):
    return demo_build(_constructor(policy_config(DEMO_FLORENCE, DEMO_HEAD, device="cpu")), device, seed)


SPEC = ModelSpec(
    name="xvla",
    components={
        "ve": Component(roots=("vlm.vision_tower",)),
        "llm": Component(roots=("vlm.language_model.encoder",)),
        "ah": Component(roots=("transformer",)),
    },
    builders={"full": _full, "demo": _demo},
)
