"""Captured pi0.5 inference: the whole chunk (prefix pass + every denoising step) as one CUDA graph.

`CapturedSampler(model, num_steps)` is called like `PI05Pytorch.sample_actions` with explicit
noise. On CUDA it captures, per batch size, one graph of `static_sampling.sample_actions` into static
input buffers on first use and afterwards only copies inputs in and replays it, so a chunk costs
one launch instead of thousands. On other devices it runs the same static code eagerly.

Make the sampler after quantization, or call `reset()` after installing, removing or changing
hooks or weights: on first use it groups each SigLIP and Gemma layer's linears (`linear_groups`,
which copy the q/k/v and gate/up weights into one matrix each and read the layers' quantizers), and
quantizers are Python, so whatever they launch is recorded at capture. Capture is one warm-up chunk plus one
recorded chunk, seconds at full size; the compiled elementwise kernels are kept across `reset()`.
Quantizers count their runs only during the warm-up and recorded chunks (a replay runs no
Python), which is enough to prove that every layer's quantizer ran.

A batch runs as one or more graphs of the sizes in `graph_sizes` (default `GRAPH_SIZES`: powers of
two and the sizes halfway between, up to 16), each captured on first use: `graph_plan` picks the
cheapest cover of the batch's rows, a replay costing its rows plus a fixed `REPLAY_COST_ROWS`, so
that a closed-loop runner, whose batches take every size as its episodes become ready at different
times, neither captures (and compiles for) every batch size nor pays much for padding (batch 13 runs
as 12 + 1, 17 as 16 + 1; padded to powers of two, 13 rows cost 16 and 17 rows 32). The last graph
of a plan may be padded with copies of its last observation. Rows do not interact, so neither the
padding nor the split changes anything in the real rows of a graph. At full size each captured graph
keeps memory in proportion to its batch (on an H200, capturing batch 1, 2, ..., 32 grew allocated
memory by ≈ 0.48 GiB and reserved memory by ≈ 1.1 GiB per batch row, to 42.6 / 83.6 GiB with the
weights; it grew the same with all graphs in one shared memory pool and one warm-up stream): the
default sizes add up to 52 rows.

Attention: the VLM prefix's 8 query heads share one KV head and are folded into one batched
product by default (`static_sampling._attention`); `prefix_sdpa=True` runs SDPA there instead, with
`attention_backends` (a list of `torch.nn.attention.SDPBackend`) ordering the kernels tried, which
also applies to the vision tower's SDPA. The defaults are the fastest in the benchmark on an H100
(`kernel_choice_sweep_b1_ms`), with the other kernels kept as fallbacks.

`tf32=True` lets float32 matrix products (lerobot keeps the SigLIP tower and projector in float32)
use TF32 tensor cores, as lerobot's own `compile_model` path does (`set_float32_matmul_precision
("high")`); the setting is scoped to capture and leaves the process default alone.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import nn
from torch.nn.attention import SDPBackend, sdpa_kernel

from vlaquantbench.models.pi05.fast import static_sampling

# Batch sizes a graph is captured for (`graph_plan`). Their sum bounds the graphs' memory.
GRAPH_SIZES = (1, 2, 3, 4, 6, 8, 12, 16)
# A replay's cost beyond its rows, in rows: pi0.5's captured chunk (2 cameras, bf16) took 21.8, 29.3,
# 44.3, 78.1, 142.6 and 277.2 ms at batch 1, 2, 4, 8, 16 and 32 on an idle H200, 13.5 ms + 8.2 ms per row.
REPLAY_COST_ROWS = 1.6
SDPA_ORDER = (SDPBackend.EFFICIENT_ATTENTION, SDPBackend.FLASH_ATTENTION, SDPBackend.CUDNN_ATTENTION,
              SDPBackend.MATH)


@functools.cache  # every policy call asks for its batch's plan; a runner meets a few dozen batch sizes
def graph_plan(batch: int, sizes: Sequence[int] = GRAPH_SIZES, replay_cost_rows: float = REPLAY_COST_ROWS) -> tuple[int, ...]:
    """The graph sizes, largest first, that `batch` rows run as: the cover of at least `batch` rows by
    `sizes` (a tuple, as plans are cached; each size usable repeatedly) of least cost, a graph costing
    its size plus `replay_cost_rows`; of equal costs, the one with fewer graphs."""
    if batch < 1:
        raise ValueError(f"a batch needs at least one row, got {batch}")
    best: list[tuple[float, int, tuple[int, ...]]] = [(0.0, 0, ())]  # rows covered -> (cost, graphs, sizes)
    for rows in range(1, batch + 1):
        best.append(min((round(best[max(rows - size, 0)][0] + size + replay_cost_rows, 9),
                         best[max(rows - size, 0)][1] + 1,
                         tuple(sorted((size, *best[max(rows - size, 0)][2]), reverse=True)))
                        for size in sizes))
    return best[batch][2]


@dataclass
class _Graph:
    graph: torch.cuda.CUDAGraph
    inputs: tuple  # static buffers: images, image masks, tokens, token masks, noise
    output: torch.Tensor


class CapturedSampler:
    """Drop-in for `model.sample_actions(images, img_masks, tokens, masks, noise=..., num_steps=...)`."""

    def __init__(self, model: nn.Module, num_steps: int, *, use_graphs: bool | None = None, tf32: bool = True,
                 attention_backends: Sequence = SDPA_ORDER, prefix_sdpa: bool = False,
                 fuse_elementwise: bool | None = None, compiler: Callable = static_sampling.inductor,
                 graph_sizes: Sequence[int] = GRAPH_SIZES):
        self.model = model
        self.graph_sizes = tuple(graph_sizes)
        self.num_steps = num_steps
        device = next(model.parameters()).device
        self.use_graphs = device.type == "cuda" if use_graphs is None else use_graphs
        self.tf32 = tf32
        self.attention_backends = list(attention_backends) if attention_backends else None
        self.prefix_sdpa = prefix_sdpa
        self.times = static_sampling.flow_times(num_steps, device)
        # Inductor fuses the elementwise work between the matrix products, op by op (compiling the
        # whole loop took over three minutes on an H100); the graph is then captured around the
        # compiled kernels as around eager ones.
        fuse = self.use_graphs if fuse_elementwise is None else fuse_elementwise
        self.ops = static_sampling.Ops(compiler) if fuse else static_sampling.EAGER_OPS
        self._graphs: dict[tuple, dict[int, _Graph]] = {}  # input shapes past the batch -> batch -> graph
        self._groups: static_sampling.ModelGroups | None = None

    def reset(self) -> None:
        """Drop every captured graph and the linear groups (after changing hooks or weights)."""
        self._graphs.clear()
        self._groups = None

    def _model_groups(self) -> static_sampling.ModelGroups:
        if self._groups is None:
            self._groups = static_sampling.ModelGroups.of(self.model)
        return self._groups

    def __call__(self, images: Sequence[torch.Tensor], img_masks: Sequence[torch.Tensor], tokens, masks, noise):
        groups = self._model_groups()
        if not self.use_graphs:
            return static_sampling.sample_actions(self.model, images, img_masks, tokens, masks, noise, self.times, self.ops,
                                              groups, self.prefix_sdpa)
        batch, inputs = noise.shape[0], (images, img_masks, tokens, masks, noise)
        by_size = self._graphs.setdefault(tuple(tuple(t.shape[1:]) for t in (*images, tokens, noise)), {})
        outputs, start = [], 0
        for size in graph_plan(batch, self.graph_sizes):
            rows = _rows(inputs, slice(start, start + size))
            if size not in by_size:
                by_size[size] = self._capture(*_padded(rows, size), groups)
            outputs.append(self._replay(by_size[size], rows))
            start += size
        return outputs[0] if len(outputs) == 1 else torch.cat(outputs)

    @staticmethod
    def _replay(entry: _Graph, inputs) -> torch.Tensor:
        """Copy `inputs` (at most the graph's rows; the rest repeat the last row) in, replay, copy the rows out."""
        rows = inputs[-1].shape[0]
        for static, value in zip(_flatten(entry.inputs), _flatten(inputs), strict=True):
            static[:rows].copy_(value, non_blocking=True)
            if static.shape[0] > rows:
                static[rows:].copy_(value[-1:].expand_as(static[rows:]), non_blocking=True)
        entry.graph.replay()
        return entry.output[:rows].clone()

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

    def _capture(self, images, img_masks, tokens, masks, noise, groups) -> _Graph:
        inputs = (
            [t.clone() for t in images],
            [t.clone() for t in img_masks],
            tokens.clone(),
            masks.clone(),
            noise.clone(),
        )

        with self._kernel_choices():
            graph, output = capture_graph(
                lambda: static_sampling.sample_actions(self.model, *inputs, self.times, self.ops, groups,
                                                   self.prefix_sdpa))
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


def _rows(inputs, rows: slice) -> tuple:
    """The sampler's inputs (tensors and lists of tensors) restricted to the batch rows `rows`."""
    return tuple([t[rows] for t in item] if isinstance(item, list | tuple) else item[rows] for item in inputs)


def _padded(inputs, size: int) -> tuple:
    """The sampler's inputs extended to `size` rows with copies of their last row."""
    def pad(t):
        return torch.cat([t, t[-1:].expand(size - t.shape[0], *t.shape[1:])]) if t.shape[0] < size else t
    return tuple([pad(t) for t in item] if isinstance(item, list | tuple) else pad(item) for item in inputs)


def _flatten(items) -> list[torch.Tensor]:
    flat = []
    for item in items:
        flat.extend(item if isinstance(item, list | tuple) else [item])
    return flat
