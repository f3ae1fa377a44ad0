"""Captured pi0.5 inference: the whole chunk (prefix pass + every denoising step) as one CUDA graph.

`CapturedSampler(model, num_steps)` is called like `PI05Pytorch.sample_actions` with explicit
noise. On CUDA it captures, per batch size, one graph of `pi05_static.sample_actions` into static
input buffers on first use and afterwards only copies inputs in and replays it, so a chunk costs
one launch instead of thousands. On other devices it runs the same static code eagerly.

The graph records the addresses of the weights, not their values, so a cell that rounds weights in
place (`quantize_`) reuses it. Hooks are Python: whatever they launch is recorded at capture, so a
sampler must be (re)captured after hooks are installed or removed -- call `reset()`; capture is one
warm-up chunk plus one recorded chunk, seconds at full size. Hook call counters advance only during
the warm-up and recorded chunks, which is enough to prove that every hook fired.

`attention_backends` (a list of `torch.nn.attention.SDPBackend`) orders the SDPA kernels tried
for the prefix; by default the memory-efficient kernel comes first, the fastest in the benchmark
on an H100 (`kernel_choice_sweep_b1_ms`), with the others kept as fallbacks.

`tf32=True` lets float32 matrix products (lerobot keeps the SigLIP tower and projector in float32)
use TF32 tensor cores, as lerobot's own `compile_model` path does (`set_float32_matmul_precision
("high")`); the setting is scoped to capture and leaves the process default alone.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn
from torch.nn.attention import SDPBackend, sdpa_kernel

from vlaquantbench.accel import pi05_static

# Quantization methods whose layers cannot run inside a CUDA graph, with the reason.
UNCAPTURABLE_METHODS = {"int8": "bitsandbytes LLM.int8() synchronizes with the host on its outlier columns"}
PREFIX_ATTENTION = (SDPBackend.EFFICIENT_ATTENTION, SDPBackend.FLASH_ATTENTION, SDPBackend.CUDNN_ATTENTION,
                    SDPBackend.MATH)


@dataclass
class _Graph:
    graph: torch.cuda.CUDAGraph
    inputs: tuple  # static buffers: images, image masks, tokens, token masks, noise
    output: torch.Tensor


class CapturedSampler:
    """Drop-in for `model.sample_actions(images, img_masks, tokens, masks, noise=..., num_steps=...)`."""

    def __init__(self, model: nn.Module, num_steps: int, *, use_graphs: bool | None = None, tf32: bool = True,
                 attention_backends: Sequence = PREFIX_ATTENTION, fuse_elementwise: bool | None = None):
        self.model = model
        self.num_steps = num_steps
        device = next(model.parameters()).device
        self.use_graphs = device.type == "cuda" if use_graphs is None else use_graphs
        self.tf32 = tf32
        self.attention_backends = list(attention_backends) if attention_backends else None
        self.times = pi05_static.flow_times(num_steps, device)
        # Inductor fuses the elementwise work between the matrix products, op by op (compiling the
        # whole loop took over three minutes on an H100); the graph is then captured around the
        # compiled kernels as around eager ones.
        fuse = self.use_graphs if fuse_elementwise is None else fuse_elementwise
        self.ops = pi05_static.compiled_ops() if fuse else pi05_static.EAGER_OPS
        self._graphs: dict[tuple, _Graph] = {}

    def reset(self) -> None:
        """Drop every captured graph (after installing or removing hooks)."""
        self._graphs.clear()

    def __call__(self, images: Sequence[torch.Tensor], img_masks: Sequence[torch.Tensor], tokens, masks, noise):
        if not self.use_graphs:
            return pi05_static.sample_actions(self.model, images, img_masks, tokens, masks, noise, self.times, self.ops)
        key = tuple(tuple(t.shape) for t in (*images, tokens, noise))
        entry = self._graphs.get(key)
        if entry is None:
            entry = self._graphs[key] = self._capture(images, img_masks, tokens, masks, noise)
        for static, value in zip(_flatten(entry.inputs), _flatten((images, img_masks, tokens, masks, noise)), strict=True):
            static.copy_(value, non_blocking=True)
        entry.graph.replay()
        return entry.output.clone()

    @contextlib.contextmanager
    def _kernel_choices(self):
        previous = torch.backends.cuda.matmul.allow_tf32
        torch.backends.cuda.matmul.allow_tf32 = self.tf32
        try:
            if self.attention_backends:
                with sdpa_kernel(self.attention_backends, set_priority=True):
                    yield
            else:
                yield
        finally:
            torch.backends.cuda.matmul.allow_tf32 = previous

    def _capture(self, images, img_masks, tokens, masks, noise) -> _Graph:
        inputs = (
            [t.clone() for t in images],
            [t.clone() for t in img_masks],
            tokens.clone(),
            masks.clone(),
            noise.clone(),
        )

        with self._kernel_choices():
            graph, output = capture_graph(lambda: pi05_static.sample_actions(self.model, *inputs, self.times, self.ops))
        return _Graph(graph, inputs, output)


def capture_graph(fn):
    """Run `fn` once on a side stream (cuBLAS/cuDNN handles, autotuning, Triton and inductor
    compilation happen there, as CUDA graph capture requires), then record it; returns the graph
    and the output tensors that each `graph.replay()` rewrites."""
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        fn()
    torch.cuda.current_stream().wait_stream(stream)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        output = fn()
    return graph, output


def _flatten(items) -> list[torch.Tensor]:
    flat = []
    for item in items:
        flat.extend(item if isinstance(item, list | tuple) else [item])
    return flat
