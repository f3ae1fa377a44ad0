"""The training step's loss and gradients as one CUDA graph (`training.cuda_graph: true`).

At the trained policy's widths (9.7 M parameters, 63 layers) an eager step launches thousands of
small kernels, and on an H100 it took 0.14 s at batch 128 and at 256 alike
(benchmarks/results/gpu_train_policy/step_rate_h100.json): the launches bound it, not the arithmetic.
`CapturedLoss` records pi0.5's forward, its flow-matching loss and the backward once, into static
input buffers (the batch, the noise and the time), and afterwards copies each step's inputs in and
replays the graph: one launch instead of thousands. The rest of the step stays eager and is the
loop's: the noise and time are drawn by the policy's own samplers outside the graph (lerobot draws
the time on the host), and gradient clipping, AdamW and the scheduler read the gradients the replay
wrote. So a captured step computes what the eager step computes, from the same random streams;
benchmarks/gpu_train_step.py checks the two against each other on the device before a run uses it.

Two rules of capture shape the code. The gradients are set to None just before capture, so that the
recorded backward allocates them in the graph's memory and every replay writes them anew: the loop
must not zero or drop them afterwards. And lerobot's pi0.5 builds its attention-mask patterns with
`torch.tensor(list, device=...)` on every forward, a host-to-device copy that capture forbids:
`_constants_made_once` makes each such constant once, in the warm-up, and hands the same tensor
back at capture; the step keeps them alive as long as the graph that reads them.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import torch

from vlaquantbench.models.pi05.fast.captured import capture_graph


@contextlib.contextmanager
def _constants_made_once() -> Iterator[dict]:
    """Within the block, `torch.tensor(data, device=<cuda>)` returns one tensor per distinct call: made
    by the first call (outside capture), returned again by later ones (at capture). Yields the made
    tensors, which the caller keeps alive."""
    made: dict[tuple, torch.Tensor] = {}
    make = torch.tensor

    def once(data, *args, dtype=None, device=None, **kwargs):
        if device is None or torch.device(device).type != "cuda" or isinstance(data, torch.Tensor):
            return make(data, *args, dtype=dtype, device=device, **kwargs)
        key = (repr(data), repr(args), dtype, str(device), repr(sorted(kwargs.items())))
        if key not in made:
            made[key] = make(data, *args, dtype=dtype, device=device, **kwargs)
        return made[key]

    torch.tensor = once
    try:
        yield made
    finally:
        torch.tensor = make


class CapturedLoss:
    """`loss_fn(policy, batch, noise, time)`'s value and its gradients as a CUDA graph, captured at the
    first call from that call's inputs and replayed at every call after; returns the loss (a copy)."""

    def __init__(self, policy: torch.nn.Module, loss_fn: Callable[..., torch.Tensor]):
        self.policy, self.loss_fn = policy, loss_fn
        self.graph = self.inputs = self.loss = self.constants = None

    def __call__(self, batch: dict[str, torch.Tensor], noise: torch.Tensor, time_: torch.Tensor) -> torch.Tensor:
        if self.graph is None:
            self.inputs = ({key: value.clone() for key, value in batch.items()}, noise.clone(), time_.clone())
            with _constants_made_once() as self.constants:
                self.graph, self.loss = capture_graph(self._loss_and_gradients)
        else:
            static_batch, static_noise, static_time = self.inputs
            if batch.keys() != static_batch.keys():
                raise ValueError(f"a captured step's batch has keys {sorted(static_batch)}, got {sorted(batch)}")
            for key, value in batch.items():
                static_batch[key].copy_(value)
            static_noise.copy_(noise)
            static_time.copy_(time_)
        self.graph.replay()
        return self.loss.clone()

    def _loss_and_gradients(self) -> torch.Tensor:
        self.policy.zero_grad(set_to_none=True)  # the backward then allocates them: in the graph's memory at capture
        loss = self.loss_fn(self.policy, *self.inputs)
        loss.backward()
        return loss.detach()
