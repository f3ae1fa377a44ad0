"""QuaRot's offline rotation of a residual stream (Ashkboos et al. 2024), generic over models.

A model declares its foldable residual streams through its component scopes
(`models.registry.Component.residual_streams`, a function of the built model returning
`ResidualStream`s); `quant.transforms.Hadamard` rotates each stream that a selected layer reads.

A stream h is written by adding module outputs (token embeddings, projectors, each layer's o_proj
and down_proj) and read only through RMSNorms, out = x / rms(x) * g with g = offset + w (Gemma:
offset 1, `x / rms * (1 + w)`; Llama: offset 0). Since rms(R x) = rms(x) for an orthonormal R,
with every writer's output rows multiplied by R (W -> R W, b -> R b, embedding vectors e -> R e)
the stream carries R h, and a norm at unit gain (w set to 1 - offset) outputs R (h / rms(h)).
Each reader W of the norm, W diag(g) (h / rms(h)) before, becomes W diag(g) R^T: the same output,
with the gain folded into it and no rotation computed at run time. A scalar scaling of the stream
(an embedding multiplied by sqrt(d)) commutes with R and needs nothing.

Whatever reads the stream other than through a declared norm's readers would see R h: a model
declares a stream only where nothing else on its action path reads it (each declaration says what
it leaves out, e.g. a final norm whose output the action path discards).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import nn

from vlaquantbench.errors import UserError

if TYPE_CHECKING:
    from vlaquantbench.quant.hadamard import BlockHadamard


# Embedding rows rotated at once: PaliGemma's 257,152 x 2,048 table would need several float32 copies
# of 2 GiB in one product.
EMBEDDING_ROWS = 16384


@dataclass(frozen=True)
class FoldableNorm:
    """An RMSNorm x / rms(x) * (gain_offset + weight) and the linears that read its output."""

    name: str
    norm: nn.Module
    readers: dict[str, nn.Linear]
    gain_offset: float

    def gain(self) -> torch.Tensor:
        return self.gain_offset + self.norm.weight.detach().float()


@dataclass(frozen=True)
class ResidualStream:
    """One residual stream: the modules writing into it (`nn.Linear`: output rows and bias;
    `nn.Embedding`: its vectors) and the norms it is read through."""

    name: str
    writers: dict[str, nn.Module]
    norms: tuple[FoldableNorm, ...]

    @property
    def width(self) -> int:
        return self.norms[0].norm.weight.numel()

    def readers(self) -> set[str]:
        return {name for norm in self.norms for name in norm.readers}


def declare_stream(model: nn.Module, name: str, writers: Sequence[str],
                   norms: Sequence[tuple[str, Sequence[str]]], gain_offset: float) -> ResidualStream:
    """A `ResidualStream` of `model` from qualified module names: writers, and (norm, its readers) pairs."""
    module = model.get_submodule
    return ResidualStream(name, {w: module(w) for w in writers},
                          tuple(FoldableNorm(n, module(n), {r: module(r) for r in readers}, gain_offset)
                                for n, readers in norms))


def rotate_stream(stream: ResidualStream, rotation: BlockHadamard) -> None:
    """Fold every norm's gain into its readers, set the norm to unit gain, multiply every writer's
    output by `rotation` (R) and every reader's input by R^T, in float32, in place: the model
    computes what it computed before."""
    with torch.no_grad():
        for norm in stream.norms:
            gain = norm.gain()
            for reader in norm.readers.values():
                folded = rotation.rotate(reader.weight.float() * gain, torch.float32)  # W diag(g) R^T
                reader.weight.copy_(folded.to(reader.weight.dtype))
            norm.norm.weight.fill_(1.0 - norm.gain_offset)
        for name, writer in stream.writers.items():
            if isinstance(writer, nn.Embedding):  # a vector per row, rotated a slice at a time
                for rows in writer.weight.split(EMBEDDING_ROWS):
                    rows.copy_(rotation.rotate(rows, torch.float32).to(rows.dtype))
            elif isinstance(writer, nn.Linear):
                rows = rotation.rotate(writer.weight.t(), torch.float32).t()  # R W
                writer.weight.copy_(rows.to(writer.weight.dtype))
                if writer.bias is not None:
                    writer.bias.copy_(rotation.rotate(writer.bias, torch.float32).to(writer.bias.dtype))
            else:
                raise TypeError(f"stream {stream.name}: writer {name} is a {type(writer).__name__}, "
                                f"neither a linear nor an embedding")


@dataclass(frozen=True)
class FoldedInput:
    """What an offline rotation did to a norm reader's input (the model computes it; no hook does):
    x -> R (x / g), g the norm's gain folded into the weight. Maps calibration rows and Hessians
    observed on the unrotated model into the layer's new input space."""

    rotation: BlockHadamard
    gain: torch.Tensor
    norm: str

    offline = True

    def _inverse_gain(self) -> torch.Tensor:
        zero = (self.gain == 0).nonzero().flatten()
        if len(zero):
            raise UserError(f"norm {self.norm} has gain 0 at channel {int(zero[0])} ({len(zero)} channels): the "
                            f"inputs its readers saw before the rotation do not determine their rotated inputs")
        return 1.0 / self.gain

    def map_rows(self, rows: torch.Tensor) -> torch.Tensor:
        return self.rotation.rotate(rows.float() * self._inverse_gain().to(rows.device), torch.float32).to(rows.dtype)

    def map_hessian(self, hessian: torch.Tensor) -> torch.Tensor:
        """R D^-1 H D^-1 R^T, D = diag(g): the second moment of the rotated inputs."""
        inverse = self._inverse_gain().to(hessian.device, hessian.dtype)
        scaled = hessian * inverse[:, None] * inverse[None, :]
        return self.rotation.map_hessian(scaled)

    def map_output(self, out: torch.Tensor) -> torch.Tensor:
        return out


@dataclass(frozen=True)
class RotatedOutput:
    """What an offline rotation did to a stream writer: its output is R times the original's."""

    rotation: BlockHadamard

    offline = True

    def map_rows(self, rows: torch.Tensor) -> torch.Tensor:
        return rows

    def map_hessian(self, hessian: torch.Tensor) -> torch.Tensor:
        return hessian

    def map_output(self, out: torch.Tensor) -> torch.Tensor:
        return self.rotation.rotate(out, torch.float32).to(out.dtype)


def is_offline(step) -> bool:
    """Whether an input step records what the model now computes itself (no hook runs it)."""
    return getattr(step, "offline", False)
