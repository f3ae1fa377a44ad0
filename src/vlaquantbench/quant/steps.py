"""The flow-step clock: which denoising step of the current action chunk a flow-matching policy is
computing, so that hooks can keep (calibration, `quant.calibration`) and use (`quant.step_static`)
statistics per flow step.

The sampler advances the clock, not the hooks: the adapter opens a chunk around each call of the
sampler and a step around each call of the model's denoise step (`attach_flow_clock` wraps lerobot's
`sample_actions` / `denoise_step`; X-VLA's adapter runs its own loop inside `clock.chunk()` and
`clock.flow_step()`). Counting hook calls instead would be wrong as soon as a layer runs a different
number of times per step (prefix/KV pass once per chunk, layers outside the action expert, a
probe's extra forwards), and one denoise step runs every batch row at the same step, so the clock is
right at any batch size. Outside a step (the prefix pass that fills the KV cache, the vision tower,
anything between chunks) `step` is None: those layers' statistics stay per layer.

    attach_flow_clock(model, "sample_actions", "denoise_step")  # the pi models' adapters, at load
    flow_clock(model).step               # 0, 1, ... inside the k-th denoise step of a chunk; else None
"""

from __future__ import annotations

import contextlib
import types
from collections.abc import Iterator

CLOCK_ATTRIBUTE = "flow_step_clock"


class FlowStepClock:
    """`step`: the index of the running flow step within the current chunk (None outside steps);
    `steps_in_chunk`: how many flow steps the current (or last) chunk has run."""

    def __init__(self) -> None:
        self.step: int | None = None
        self.steps_in_chunk = 0

    @contextlib.contextmanager
    def chunk(self) -> Iterator[None]:
        self.steps_in_chunk, self.step = 0, None
        try:
            yield
        finally:
            self.step = None

    @contextlib.contextmanager
    def flow_step(self) -> Iterator[int]:
        self.step = self.steps_in_chunk
        try:
            yield self.step
        finally:
            self.step = None
            self.steps_in_chunk += 1


def flow_clock(model) -> FlowStepClock | None:
    """The clock the adapter attached to `model` (None: a policy without a flow-matching loop)."""
    return getattr(model, CLOCK_ATTRIBUTE, None)


def attach_flow_clock(model, chunk_method: str | None = None, step_method: str | None = None) -> FlowStepClock:
    """Attach a clock to `model`, for an adapter whose own loop advances it; with method names, also
    wrap, on the instance, the model's sampler (`chunk_method`: one chunk per call) and its denoise
    step (`step_method`: one flow step per call). The wrappers are methods bound to `model`
    (`types.MethodType`) that look the clock up on their instance, so a deep copy of the model
    (quantization tests copy the demo policy) gets wrappers and a clock of its own."""
    setattr(model, CLOCK_ATTRIBUTE, FlowStepClock())

    def clocked_chunk(self, *args, **kwargs):
        with flow_clock(self).chunk():
            return getattr(type(self), chunk_method)(self, *args, **kwargs)

    def clocked_step(self, *args, **kwargs):
        with flow_clock(self).flow_step():
            return getattr(type(self), step_method)(self, *args, **kwargs)

    if chunk_method is not None:
        setattr(model, chunk_method, types.MethodType(clocked_chunk, model))
    if step_method is not None:
        setattr(model, step_method, types.MethodType(clocked_step, model))
    return flow_clock(model)
