"""Pre-quantization transforms: rewrite selected layers, without changing what they compute, before
a method quantizes them. `QuantConfig.transforms` is an ordered list; `quantize_` applies each in turn,
then runs the method on the transformed weights.

A transform changes weights in place and returns, per layer it changed, the steps the layer's input
must take first (callables on the input tensor, e.g. `InputTransform(smooth=d, clip=c)`): with them,
the layer's output is unchanged up to the transform's own approximation (clipping). It sees the
steps earlier transforms left (`selection.inputs`). An offline step (`quant.rotation.FoldedInput`,
`RotatedOutput`: `offline` True) records what the transformed model now computes itself; no hook
runs it, but it maps calibration rows and Hessians into the layer's new input space and its
reference outputs into its new output space. Methods that compose
with transforms (`rtn`, `gptq`) run those steps, in order, ahead of their activation quantization
(`input_steps`); the others refuse a non-empty list.

    Smoothing   rollout smoothing and clipping (paper `app:calib`): W diag(d), x / d clipped at the
                calibrated quantile, on the layers of the calibrated components
    Hadamard    QuaRot's block-Hadamard rotation R: residual streams whose RMSNorms fold (pi0 and
                pi0.5's VLM, pi0's expert) rotated offline, the norms' gains and R folded into the
                weights that write and read them; every other selected input (down_proj/o_proj and
                fc2-type layers, LayerNorm models, pi0.5's adaptive-norm expert) rotated online,
                W R^T (R x) = W x (see `Hadamard`)

Methods that take a layer's calibration Hessian (GPTQ) map it into the transformed input space
through the step's `map_hessian`; a step without one (smoothing's clip is not linear) is refused there.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from vlaquantbench.errors import UserError
from vlaquantbench.quant.calibration import FLOOR, CalibrationSettings, CalibrationStats, smoothing_factors
from vlaquantbench.quant.hadamard import BlockHadamard
from vlaquantbench.quant.input_transform import InputTransform
from vlaquantbench.quant.presets import Preset
from vlaquantbench.quant.rotation import FoldedInput, RotatedOutput, is_offline, rotate_stream

if TYPE_CHECKING:
    from vlaquantbench.quant.scope import Selection


class Transform:
    """What `quantize_` asks of a pre-quantization transform: `check_after` first (every transform, before
    any changes a weight), then `apply` in list order; `description` extends the cell's quant_format."""

    description = ""  # empty: the method's format already says it (smoothing: the calibration settings)
    title = "a transform"  # what refusals call it

    def check_after(self, earlier: Sequence[Transform], selection: Selection, stats: CalibrationStats | None) -> None:
        """Refuse, naming the conflict, to follow the transforms `earlier` in the list; by default it follows any."""

    def runtime_step_layers(self, selection: Selection, stats: CalibrationStats | None) -> list[str]:
        """The selected layers whose input `apply` will give a step computed at run time (a division, an
        online rotation), changing nothing: what a later transform that cannot follow such a step asks."""
        raise NotImplementedError

    def apply(self, selection: Selection, stats: CalibrationStats | None) -> dict[str, tuple[Callable, ...]]:
        """Rewrite the selected layers' weights in place; per layer changed, the steps its input takes first."""
        raise NotImplementedError


@dataclass(frozen=True)
class Smoothing(Transform):
    """SmoothQuant-style migration from rollout statistics, d_j = max(a_j^alpha / w_j^(1-alpha), 1e-5)
    (`quant.calibration.smoothing_factors`), and clipping of x / d at quantile_j / d_j (none when the
    settings' quantile is None: then an exact identity before quantization)."""

    settings: CalibrationSettings
    title = "rollout smoothing"

    def runtime_step_layers(self, selection: Selection, stats: CalibrationStats | None) -> list[str]:
        """The selected layers it divides: those of the calibrated components that calibration observed
        (the others stay untransformed)."""
        return [name for name in selection.flat() if selection.component_of(name) in self.settings.components
                and stats is not None and name in stats.layers]

    def apply(self, selection: Selection, stats: CalibrationStats | None) -> dict[str, tuple[Callable, ...]]:
        steps = {}
        layers = selection.flat()
        for name in self.runtime_step_layers(selection, stats):
            layer, layer_stats = layers[name], stats.layers[name]
            with torch.no_grad():
                smooth = smoothing_factors(layer_stats.absmax, layer.weight, self.settings.alpha)
                clip = None
                if self.settings.quantile is not None:
                    clip = (layer_stats.quantile.float().to(smooth.device) / smooth).clamp_min(FLOOR)
                layer.weight.copy_((layer.weight.float() * smooth).to(layer.weight.dtype))
            steps[name] = (InputTransform(smooth=smooth, clip=clip),)
        return steps


@dataclass(frozen=True)
class Hadamard(Transform):
    """QuaRot's rotations (Ashkboos et al. 2024) with R = blockdiag(H_b, ..., H_b), H_b the Sylvester
    Hadamard matrix of order b scaled by 1/sqrt(b) (orthonormal), b the largest power of two dividing
    the width (`BlockHadamard`; the whole width for every Gemma layer of pi0 and pi0.5). Rotating
    spreads an outlier channel over b channels, which is what lets 4-bit per-token activation grids
    keep the rest. All folding is in float32, then the weights' dtype.

    Offline, where a residual stream's norms fold (`quant.rotation`; each model declares its
    streams through its component scopes): every writer's output rows are multiplied by R, every
    RMSNorm's gain is folded into the linears reading it and the norm set to unit gain, and those
    readers take R^T on their input columns. Their inputs arrive rotated: their hooks only quantize.
    A stream is rotated when the selection selects one of its readers (a scope that selects none,
    e.g. `ah` for the VLM's stream, leaves it as it is); its unselected writers and readers are
    rotated too, so the whole model stays function preserving, and stay unquantized.
        pi0, pi0.5   the VLM's Gemma stream (token embedding and projector write it; q/k/v and
                     gate/up read it); pi0's expert stream (state_proj, action_time_mlp_out write
                     it; its final norm folds into action_out_proj). pi0.5's expert norms are
                     adaptive (a per-sample scale and shift from the flow time): not foldable.
        OFT          not declared: its LLaMA's final norm feeds the action head's LayerNorm over
                     7 concatenated hidden states, which cannot read a rotated stream.
        LayerNorm    SigLIP, DINOv2 and every X-VLA norm subtract a mean and add a bias, which do
                     not commute with R: not declared, rotated online.
    Online, on every other selected linear (down_proj/o_proj and fc2-type layers, whose inputs
    come from inside a block, and every layer of a stream that is not folded): R^T folded into the
    weight and the input rotated at run time by `BlockHadamard` (W R^T (R x) = W x), inside pi0.5's
    captured sampler with the op producing it (`quant.hooks.Rotated`).

    It rotates what the selection selects, `nn.Linear` layers: fused ones (X-VLA's qkv) like any
    other, never a convolution (patch embeddings, DaViT's depthwise position convolutions stay as
    they are). An odd input width has block 1, R = I: such a layer is quantized unrotated (the demo
    OpenVLA-OFT's 119-wide SigLIP fc2; no released width of pi0, pi0.5, X-VLA or OFT is odd).
    Rollout smoothing before an offline rotation is refused (a folded reader's input is computed
    by the model, where no per-channel division can run first)."""

    title = "the Hadamard rotation"
    description = ("residual streams rotated offline where their RMSNorms fold, other inputs rotated online "
                   "(QuaRot block-Hadamard)")

    def check_after(self, earlier: Sequence[Transform], selection: Selection, stats: CalibrationStats | None) -> None:
        """Refuse to follow a transform that gives a reader this rotation folds a run-time input step: the
        folded reader's input is computed by the model, where no step can run first."""
        layers = selection.flat()
        for transform in earlier:
            stepped = set(transform.runtime_step_layers(selection, stats))
            for stream in self._rotated_streams(selection):
                if conflicts := [name for name in _folded_readers(stream, layers) if name in stepped]:
                    raise UserError(f"the offline rotation of residual stream {stream.name!r} cannot follow "
                                    f"{transform.title} of its reader {conflicts[0]}: run {self.title} without it")

    def runtime_step_layers(self, selection: Selection, stats: CalibrationStats | None) -> list[str]:
        """The layers rotated online: every selected layer that no rotated stream's norm feeds."""
        layers = selection.flat()
        folded = {name for stream in self._rotated_streams(selection) for name in _folded_readers(stream, layers)}
        return [name for name in layers if name not in folded]

    @staticmethod
    def _rotated_streams(selection: Selection) -> list:
        """The residual streams it rotates offline: those whose readers the selection selects."""
        layers = selection.flat()
        return [stream for stream in selection.streams if stream.readers() & set(layers)]

    def apply(self, selection: Selection, stats: CalibrationStats | None) -> dict[str, tuple[Callable, ...]]:
        layers = selection.flat()
        steps: dict[str, tuple[Callable, ...]] = {}
        for stream in self._rotated_streams(selection):  # one nothing selected reads is left as it is
            rotation = BlockHadamard(stream.width, stream.norms[0].norm.weight.device)
            folded = {name: FoldedInput(rotation, norm.gain(), norm.name)
                      for name, norm in _folded_readers(stream, layers).items()}
            rotate_stream(stream, rotation)
            steps.update({name: (step,) for name, step in folded.items()})
            steps.update({name: (RotatedOutput(rotation),) for name in stream.writers if name in layers})
        for name, layer in layers.items():
            if name in steps and isinstance(steps[name][0], FoldedInput):
                continue
            rotation = BlockHadamard(layer.in_features, layer.weight.device)
            with torch.no_grad():
                layer.weight.copy_(rotation.rotate(layer.weight, torch.float32).to(layer.weight.dtype))
            steps[name] = (*steps.get(name, ()), rotation)
        return steps


def _folded_readers(stream, layers: dict) -> dict:
    """The selected linears reading `stream` through its norms, in the stream's order: {name: norm}."""
    return {name: norm for norm in stream.norms for name in norm.readers if name in layers}


def input_steps(steps: Sequence[Callable], preset: Preset) -> Callable:
    """One layer's input transform: the transforms' steps in order, then the preset's activation
    quantization. A single smoothing step or a single rotation folds into one `InputTransform` (the
    form the fast paths know: rotate, divide, clip, quantize; pi0.5's captured sampler computes a
    rotation and quantization once per input that several layers read)."""
    quantize = InputTransform(act_bits=preset.act_bits, act_format=preset.act_format)
    steps = [step for step in steps if not is_offline(step)]  # what the rotated model computes itself
    if not steps:
        return quantize
    if len(steps) == 1 and isinstance(steps[0], BlockHadamard):  # the form the captured fast path fuses
        return InputTransform(rotation=steps[0], act_bits=preset.act_bits, act_format=preset.act_format)
    if len(steps) == 1 and isinstance(steps[0], InputTransform) and steps[0].act_bits is None:
        return InputTransform(smooth=steps[0].smooth, clip=steps[0].clip, act_bits=preset.act_bits,
                              act_format=preset.act_format)
    return _Chain((*steps, quantize))


@dataclass(frozen=True)
class _Chain:
    """Several input steps applied in order."""

    steps: tuple[Callable, ...]

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        for step in self.steps:
            x = step(x)
        return x

    @property
    def is_identity(self) -> bool:
        return False
