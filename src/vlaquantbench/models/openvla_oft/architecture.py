"""OpenVLA-OFT (`moojink/openvla-7b-oft-finetuned-libero-*`) architecture, from its published sizes.

No library ships this policy as one module, so it is assembled here: timm builds the two vision
backbones and transformers builds LLaMA-2-7B; the projectors and the L1-regression action head are
small MLPs written from their published shapes. Module names follow the released checkpoint so
the authors' patterns (`action_head*.fc2`, `*mlp_resnet_blocks*`) select the same layers.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

LLM_DIM = 4096
ACTION_DIM = 7
PROPRIO_DIM = 8
CHUNK = 8  # actions decoded in parallel per forward pass
VISION_DIMS = (1024, 1152)  # DINOv2 ViT-L/14 + SigLIP so400m/14 patch features, concatenated
DINOV2 = "vit_large_patch14_reg4_dinov2.lvd142m"
SIGLIP = "vit_so400m_patch14_siglip_224"
IMAGE_SIZE = 224


@dataclass(frozen=True)
class OFTSizes:
    """Widths of one OpenVLA-OFT build; depths, head layout and module names never change."""

    llm_dim: int = LLM_DIM
    llm_mlp: int = 11008
    llm_heads: int = 32
    vocab: int = 32064  # LLaMA-2's 32000 tokens padded to 32064 (OpenVLA's 256 action bins)
    dino: tuple[int, int] = (VISION_DIMS[0], 16)  # embedding width, heads
    siglip: tuple[int, int] = (VISION_DIMS[1], 16)

    @property
    def vision_dim(self) -> int:
        return self.dino[0] + self.siglip[0]


RELEASED = OFTSizes()
# Demo widths: 24 DINOv2 and 27 SigLIP blocks, 32 LLaMA layers, the same 224-px/14 patch grid.
DEMO = OFTSizes(llm_dim=64, llm_mlp=128, llm_heads=4, vocab=512, dino=(32, 2), siglip=(32, 2))


class FusedVisionBackbone(nn.Module):
    """Patch features of DINOv2 and SigLIP, each taken from its second-to-last block, concatenated."""

    def __init__(self, sizes: OFTSizes = RELEASED, image_size: int = IMAGE_SIZE):
        super().__init__()
        import timm

        def vit(name, width_heads):
            width, heads = width_heads
            return timm.create_model(name, pretrained=False, num_classes=0, img_size=image_size, embed_dim=width,
                                     num_heads=heads)

        self.featurizer = vit(DINOV2, sizes.dino)
        self.fused_featurizer = vit(SIGLIP, sizes.siglip)

    def forward(self, dino_pixels: torch.Tensor, siglip_pixels: torch.Tensor) -> torch.Tensor:
        features = []
        for vit, pixels in ((self.featurizer, dino_pixels), (self.fused_featurizer, siglip_pixels)):
            features.append(vit.get_intermediate_layers(pixels, n={len(vit.blocks) - 2})[0])
        return torch.cat(features, dim=-1)


class FusedProjector(nn.Module):
    """Vision features (2176) to LLM embeddings (4096) through a 4x-wide hidden layer."""

    def __init__(self, vision_dim: int = sum(VISION_DIMS), llm_dim: int = LLM_DIM):
        super().__init__()
        self.fc1 = nn.Linear(vision_dim, 4 * vision_dim)
        self.fc2 = nn.Linear(4 * vision_dim, llm_dim)
        self.fc3 = nn.Linear(llm_dim, llm_dim)
        self.act = nn.GELU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc3(self.act(self.fc2(self.act(self.fc1(x)))))


class ProprioProjector(nn.Module):
    """Robot state (8) to one LLM token embedding."""

    def __init__(self, proprio_dim: int = PROPRIO_DIM, llm_dim: int = LLM_DIM):
        super().__init__()
        self.fc1 = nn.Linear(proprio_dim, llm_dim)
        self.fc2 = nn.Linear(llm_dim, llm_dim)
        self.act = nn.GELU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class ResidualBlock(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.ffn = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, dim), nn.ReLU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.ffn(x)


class MLPResNet(nn.Module):
    """fc1, two residual blocks, fc2: the 4-linear action MLP of OFT's L1 regression head."""

    def __init__(self, in_dim: int, hidden_dim: int, out_dim: int, num_blocks: int = 2):
        super().__init__()
        self.layer_norm1 = nn.LayerNorm(in_dim)
        self.fc1 = nn.Linear(in_dim, hidden_dim)
        self.relu = nn.ReLU()
        self.mlp_resnet_blocks = nn.ModuleList(ResidualBlock(hidden_dim) for _ in range(num_blocks))
        self.layer_norm2 = nn.LayerNorm(hidden_dim)
        self.fc2 = nn.Linear(hidden_dim, out_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.relu(self.fc1(self.layer_norm1(x)))
        for block in self.mlp_resnet_blocks:
            x = block(x)
        return self.fc2(self.layer_norm2(x))


class L1RegressionActionHead(nn.Module):
    """Maps each action token's 7 per-dimension hidden states (7 x 4096, flattened) to a 7-D action."""

    def __init__(self, llm_dim: int = LLM_DIM, action_dim: int = ACTION_DIM):
        super().__init__()
        self.model = MLPResNet(in_dim=llm_dim * action_dim, hidden_dim=llm_dim, out_dim=action_dim)

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:  # [B, chunk, action_dim * llm_dim]
        return self.model(hidden)


class OpenVLAOFT(nn.Module):
    """The five parts of the policy, named like the released checkpoint's modules."""

    def __init__(self, sizes: OFTSizes = RELEASED):
        super().__init__()
        from transformers import LlamaConfig, LlamaForCausalLM

        self.sizes = sizes
        self.vision_backbone = FusedVisionBackbone(sizes)
        self.projector = FusedProjector(sizes.vision_dim, sizes.llm_dim)
        llama = LlamaConfig(
            vocab_size=sizes.vocab, hidden_size=sizes.llm_dim, intermediate_size=sizes.llm_mlp, num_hidden_layers=32,
            num_attention_heads=sizes.llm_heads, num_key_value_heads=sizes.llm_heads, max_position_embeddings=2048,
        )
        self.language_model = LlamaForCausalLM(llama)
        self.proprio_projector = ProprioProjector(PROPRIO_DIM, sizes.llm_dim)
        self.action_head = L1RegressionActionHead(sizes.llm_dim, ACTION_DIM)

    def restore_rotary_embedding(self) -> None:
        """Recompute LLaMA's rotary frequencies on the CPU: a non-persistent buffer, which a model built
        on the meta device and loaded with `assign=True` would otherwise keep on the meta device."""
        llama = self.language_model.model
        with torch.device("cpu"):
            llama.rotary_emb = type(llama.rotary_emb)(config=llama.config)

    def forward(self, dino_pixels: torch.Tensor, siglip_pixels: torch.Tensor, proprio: torch.Tensor,
                prompt_embeds: torch.Tensor) -> torch.Tensor:
        """Parallel decoding: one LLM pass over [BOS, image patches, proprio token, prompt, CHUNK x 7
        zeroed action slots, stop]; the slots' last hidden states, 7 per action, feed the L1 head.

        `dino_pixels`/`siglip_pixels`: [B * views, 3, 224, 224] per backbone, views of one sample
        consecutive; `prompt_embeds`: [B, T, D] token embeddings of BOS + prompt + stop, stop last.
        Attention is bidirectional over the whole sequence, as in OFT's parallel decoding.
        """
        batch = proprio.shape[0]
        patches = self.projector(self.vision_backbone(dino_pixels, siglip_pixels))  # [B * views, P, D]
        patches = patches.reshape(batch, -1, patches.shape[-1])
        proprio_token = self.proprio_projector(proprio).unsqueeze(1)
        slots = prompt_embeds.new_zeros(batch, CHUNK * ACTION_DIM, prompt_embeds.shape[-1])
        sequence = torch.cat([prompt_embeds[:, :1], patches, proprio_token, prompt_embeds[:, 1:-1], slots,
                              prompt_embeds[:, -1:]], dim=1)
        length = sequence.shape[1]
        # A float mask of zeros: every position attends to every other (no causal mask).
        everything = sequence.new_zeros(batch, 1, length, length)
        hidden = self.language_model.model(inputs_embeds=sequence, attention_mask=everything).last_hidden_state
        actions = hidden[:, -1 - CHUNK * ACTION_DIM : -1].reshape(batch, CHUNK, ACTION_DIM * hidden.shape[-1])
        return self.action_head(actions)
