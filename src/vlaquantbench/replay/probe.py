"""What a flow-matching policy computed inside one call, captured without editing the adapter.

The probe wraps two methods of the policy model on the instance (`sample_actions`, which returns
the normalized chunk, and `denoise_step`, which receives the state x_t entering each flow update)
and prepends forward pre-hooks on the observed layers, so it sees their raw inputs before any
activation quantizer hook runs. Everything is split per batch element.
"""

from __future__ import annotations

import fnmatch
from contextlib import contextmanager

import numpy as np
import torch
from torch import nn

from vlaquantbench.errors import UserError
from vlaquantbench.replay.composition import activation_input_stats


class PolicyProbe:
    def __init__(self, model: nn.Module, observe: list[str], action_dims: int):
        self.model = model
        self.action_dims = action_dims
        self.layers = {n: m for n, m in model.named_modules()
                       if isinstance(m, nn.Linear) and any(fnmatch.fnmatchcase(n, p) for p in observe)}
        if not self.layers:
            raise UserError(f"probe patterns {observe} select no linear layer of {type(model).__name__}")
        self._handles: list = []
        self._reset()

    def _reset(self) -> None:
        self.chunks: np.ndarray | None = None
        self.states: list[np.ndarray] = []  # per denoising step: [batch, horizon, state_dims]
        self.inputs: dict[str, list[np.ndarray]] = {n: [] for n in self.layers}  # per forward: [batch, cols]

    def __enter__(self) -> "PolicyProbe":
        sample, denoise = self.model.sample_actions, self.model.denoise_step
        # what the instance itself held (the adapter's flow-step clock wrappers, `quant.steps`), restored on exit
        self._own = {name: vars(self.model)[name] for name in ("sample_actions", "denoise_step") if name in vars(self.model)}

        def sample_actions(*args, **kwargs):
            out = sample(*args, **kwargs)
            self.chunks = out.detach().float().cpu().numpy()[..., : self.action_dims]
            return out

        def denoise_step(*args, **kwargs):
            x_t = kwargs["x_t"] if "x_t" in kwargs else args[2]
            self.states.append(x_t.detach().float().cpu().numpy())
            return denoise(*args, **kwargs)

        self.model.sample_actions, self.model.denoise_step = sample_actions, denoise_step
        for name, layer in self.layers.items():
            self._handles.append(layer.register_forward_pre_hook(self._observer(name), prepend=True))
        return self

    def __exit__(self, *exc) -> None:
        del self.model.sample_actions, self.model.denoise_step  # back to the class methods
        vars(self.model).update(self._own)  # or to the instance's own wrappers
        for handle in self._handles:
            handle.remove()
        self._handles.clear()

    def _observer(self, name: str):
        def hook(module, args):
            x = args[0].detach().float().cpu().numpy()
            self.inputs[name].append(np.stack([activation_input_stats(x[b]) for b in range(x.shape[0])]))

        return hook

    @contextmanager
    def call(self):
        """Scope one policy call; afterwards `take(i)` gives batch element i's arrays."""
        self._reset()
        yield self
        if self.chunks is None:
            raise RuntimeError("the policy call never reached sample_actions: nothing was captured")

    def take(self, i: int) -> dict[str, np.ndarray]:
        """chunk [horizon, action_dims]; flow_states [steps, horizon, state_dims];
        inputs [forwards, layers, columns] (layers in `self.layers` order)."""
        per_layer = [np.stack([s[i] for s in self.inputs[n]]) for n in self.layers]
        return {
            "chunk": self.chunks[i],
            "flow_states": np.stack([s[i] for s in self.states]),
            "inputs": np.stack(per_layer, axis=1),
        }


def torch_rng_state(generator: torch.Generator) -> np.ndarray:
    return generator.get_state().numpy().copy()
