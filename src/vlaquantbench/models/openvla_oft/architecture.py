"""OpenVLA-OFT (`moojink/openvla-7b-oft-finetuned-libero-*`) architecture, from its published sizes.

No library ships this policy as one module, so it is assembled here: timm builds the two vision
backbones and transformers builds LLaMA-2-7B; the projectors and the L1-regression action head are
small MLPs written from their published shapes. Module names follow the released checkpoint so
the authors' patterns (`action_head*.fc2`, `*mlp_resnet_blocks*`) select the same layers.
"""

from __future__ import annotations

import torch
from torch import nn

LLM_DIM = 4096
ACTION_DIM = 7
PROPRIO_DIM = 8
VISION_DIMS = (1024, 1152)  # DINOv2 ViT-L/14 + SigLIP so400m/14 patch features, concatenated
DINOV2 = "vit_large_patch14_reg4_dinov2.lvd142m"
SIGLIP = "vit_so400m_patch14_siglip_224"


class FusedVisionBackbone(nn.Module):
    """Patch features of DINOv2 and SigLIP, each taken from its second-to-last block, concatenated."""

    def __init__(self, image_size: int = 224):
        super().__init__()
        import timm

        self.featurizer = timm.create_model(DINOV2, pretrained=False, num_classes=0, img_size=image_size)
        self.fused_featurizer = timm.create_model(SIGLIP, pretrained=False, num_classes=0, img_size=image_size)

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

    def __init__(self):
        super().__init__()
        from transformers import LlamaConfig, LlamaForCausalLM

        self.vision_backbone = FusedVisionBackbone()
        self.projector = FusedProjector()
        # LLaMA-2-7B with OpenVLA's vocabulary padded to 32064 (256 action bins over 32000 tokens).
        llama = LlamaConfig(
            vocab_size=32064, hidden_size=LLM_DIM, intermediate_size=11008, num_hidden_layers=32,
            num_attention_heads=32, num_key_value_heads=32, max_position_embeddings=2048,
        )
        self.language_model = LlamaForCausalLM(llama)
        self.proprio_projector = ProprioProjector()
        self.action_head = L1RegressionActionHead()
