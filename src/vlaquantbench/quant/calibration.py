"""Rollout calibration (paper appendix `app:calib`): observe linear inputs during unquantized
episodes, then smooth and clip them when quantizing.

Collecting statistics (the runner's calibrate rule, `vlaquantbench.runner.calibration`)::

    from vlaquantbench.quant import CalibrationSettings, select_layers
    from vlaquantbench.quant.calibration import calibration_key, keyed_fields, observe, save_stats

    settings = CalibrationSettings(alpha=0.5, quantile=0.999, components=("ah",))
    fields = dict(model="pi05", checkpoint=..., revision=..., init_states=[20, 21], tasks=1, seed=0,
                  settings=settings, code_revision=...)
    layers = {}
    for component in settings.components:
        layers.update(select_layers(policy, spec.components, component).flat())
    with observe(layers, quantile=settings.quantile) as observer:
        ...  # run the unquantized episodes
    stats = observer.stats(calibration_key(**fields), keyed_fields(*fields.values()))
    save_stats(stats, cache_dir / f"{stats.key}.pt")

Using them: `QuantConfig.from_preset(..., calibration=settings, stats=load_stats(path))`. Observe
every layer of the calibrated components (not only a subset) so one cache serves all subsets.

Per layer and input channel j the observer keeps `absmax[j]`, the running max of |a_j| over every
token of every call, and `quantile[j]`, the max over calls of that call's per-channel `quantile`
of |a_j| (not a quantile of all tokens pooled). A single-token call contributes its magnitude; a
call larger than `QUANTILE_MAX_ELEMENTS` is sampled at a fixed token stride for the quantile.
With `sample_rows` > 0 (AWQ statistics, `vlaquantbench.quant.awq`) it also keeps the per-channel
sum of |a_j| over all rows (`absmean`) and at most `sample_rows` input rows: the rows whose index
in the stream of all observed rows is a multiple of a stride that doubles whenever the sample would
overflow, so the sample is deterministic and evenly spread over every call.
With `hessian` (GPTQ statistics, `vlaquantbench.quant.gptq`) it also keeps X^T X over every observed
row in float32 (`hessian`), on the layer's device while observing and until saved.
With `step_scales` (per-denoising-step scales, `vlaquantbench.quant.step_static`) and the policy's
flow-step clock (`quant.steps`), it also keeps, for the calls made inside a flow step, the
per-tensor max |x| of each step (`step_absmax[k]`, over every token, channel and batch row of step
k of every chunk): per tensor because a static activation scale of an integer product is one number
per layer (a per-channel one would not factor out of the sum over channels); a max, so batching
rows together does not change it. Layers that never run inside a step (the prefix pass, the vision
tower) keep none.
Which of these a calibration collects is what its cell's method declares (`quant.methods`
statistics kinds; `CalibrationSettings.for_cell`).
At quantization, with a_j and w_j = max_i |W_ij| floored at 1e-5,
d_j = max(a_j^alpha / w_j^(1 - alpha), 1e-5); weights become W diag(d), and the input hook divides
by d, clips at max(quantile_j / d_j, 1e-5), then quantizes (`vlaquantbench.quant.hooks`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from vlaquantbench.atomic import atomic_write
from vlaquantbench.errors import UserError
from vlaquantbench.quant.steps import FlowStepClock

FLOOR = 1e-5
QUANTILE_MAX_ELEMENTS = 2**24  # torch.quantile's input limit


@dataclass(frozen=True)
class CalibrationSettings:
    """Smoothing strength, clip quantile (None: smooth without clipping, an exact identity
    before quantization) and the components whose layers are smoothed and clipped."""

    alpha: float | None = 0.5  # None: no rollout smoothing (statistics for AWQ only)
    quantile: float | None = 0.999
    components: tuple[str, ...] = ("ah",)
    sample_rows: int = 0  # > 0: also keep mean |a_j| and this many input rows per layer (AWQ, GPTQ)
    hessian: bool = False  # also keep X^T X per layer (GPTQ)
    step_scales: bool = False  # also keep max |x| per flow step, for layers that run inside steps

    @classmethod
    def for_cell(cls, calibration: Any, calibrated_components: Sequence[str]) -> CalibrationSettings:
        """The settings of a cell's `calibration` config (a `cells.CellCalibration`, not imported: cells
        imports quant's registry). Smoothing statistics
        cover the components the model calibrates (`calibrated_components`: the pi models leave their MP
        uncalibrated, paper app:calib); a method's input rows or Hessians cover every component of the
        scope, as the method quantizes them all."""
        sample_rows, hessian = calibration.sample_rows or 0, bool(calibration.hessian)
        step_scales = bool(calibration.step_scales)
        every = sample_rows or hessian or step_scales
        components = tuple(c for c in calibration.components if every or c in calibrated_components)
        return cls(alpha=calibration.alpha, quantile=calibration.quantile, components=components,
                   sample_rows=sample_rows, hessian=hessian, step_scales=step_scales)

    def observe(self, layers: Mapping[str, nn.Linear],
                clock: FlowStepClock | None = None) -> contextlib.AbstractContextManager[ActivationObserver]:
        """`observe` collecting exactly what these settings use (per-step scales: on `clock`'s steps)."""
        return observe(layers, quantile=self.quantile, sample_rows=self.sample_rows, hessian=self.hessian,
                       clock=clock if self.step_scales else None)


@dataclass
class ChannelStats:
    absmax: torch.Tensor  # [in_features], running max |a_j|
    quantile: torch.Tensor  # [in_features], max over calls of the per-call quantile of |a_j|
    calls: int = 0
    abs_sum: torch.Tensor | None = None  # [in_features] float64, sum of |a_j| over all rows (sample_rows > 0)
    rows: int = 0  # rows (tokens) observed
    samples: torch.Tensor | None = None  # [<= sample_rows, in_features], rows at `sample_stride`
    sample_stride: int = 1
    hessian: torch.Tensor | None = None  # [in_features, in_features] float32, X^T X over every row (hessian)
    step_absmax: torch.Tensor | None = None  # [flow steps] float32, max |x| of each step's calls (step_scales)

    @property
    def absmean(self) -> torch.Tensor | None:
        """Mean |a_j| over every observed row, or None when rows were not tracked."""
        return None if self.abs_sum is None else (self.abs_sum / max(self.rows, 1)).float()


@dataclass
class CalibrationStats:
    """Observed statistics of one calibration run plus the fields its cache key was made from."""

    key: str
    keyed_fields: dict
    layers: dict[str, ChannelStats] = field(default_factory=dict)

    def provenance(self, settings: CalibrationSettings) -> dict:
        """The header's `act_calib` record: what was calibrated, on which rollouts, from which cache."""
        return {
            "components": list(settings.components),
            "alpha": settings.alpha,
            "clip_quantile": settings.quantile,
            "cache": f"{self.key}.pt",
            "observed_layers": len(self.layers),
            **self.keyed_fields,
        }


def calibration_key(
    *,
    model: str,
    checkpoint: str,
    revision: str | None,
    init_states: Sequence[int],
    tasks: int,
    seed: int,
    settings: CalibrationSettings,
    code_revision: str | None,
) -> str:
    """12-hex cache key over every field that changes the collected statistics or their use."""
    fields = keyed_fields(model, checkpoint, revision, init_states, tasks, seed, settings, code_revision)
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:12]


def keyed_fields(model, checkpoint, revision, init_states, tasks, seed, settings, code_revision) -> dict:
    return {
        "model": model,
        "checkpoint": checkpoint,
        "revision": revision,
        "init_states": [int(s) for s in init_states],
        "tasks": int(tasks),
        "seed": int(seed),
        "alpha": None if settings.alpha is None else float(settings.alpha),
        "quantile": settings.quantile,
        "components": sorted(settings.components),
        "code_revision": code_revision,
        # only when requested, so the keys of existing smoothing-only caches stay what they were
        **({"sample_rows": int(settings.sample_rows)} if settings.sample_rows else {}),
        **({"hessian": True} if settings.hessian else {}),
        **({"step_scales": True} if settings.step_scales else {}),
    }


def per_call_quantile(x: torch.Tensor, q: float) -> torch.Tensor:
    """Per-channel `q`-quantile of |x| over the tokens of one call (leading dims are tokens)."""
    tokens = x.detach().abs().float().reshape(-1, x.shape[-1])
    if tokens.shape[0] == 1:
        return tokens[0]
    max_tokens = max(1, QUANTILE_MAX_ELEMENTS // tokens.shape[1])
    if tokens.shape[0] > max_tokens:
        tokens = tokens[:: math.ceil(tokens.shape[0] / max_tokens)]
    return torch.quantile(tokens, q, dim=0)


def keep_strided_rows(
    samples: torch.Tensor | None, stride: int, seen: int, rows: torch.Tensor, limit: int
) -> tuple[torch.Tensor, int]:
    """Add `rows` (stream positions `seen`, `seen + 1`, ...) to `samples`, which holds the rows at
    every multiple of `stride` before `seen`; the stride doubles (dropping every other kept row)
    until at most `limit` rows remain. Only the kept rows leave the device. Returns (sample, stride)."""
    total = seen + rows.shape[0]
    new_stride = stride
    while -(-total // new_stride) > limit:  # multiples of the stride below `total`
        new_stride *= 2
    picked = rows[(-seen) % new_stride :: new_stride].cpu()
    if samples is None:
        return picked, new_stride
    return torch.cat([samples[:: new_stride // stride], picked]), new_stride


class ActivationObserver:
    """Forward pre-hooks collecting `ChannelStats` on linear inputs; use through `observe`."""

    def __init__(self, layers: Mapping[str, nn.Linear], quantile: float | None, sample_rows: int = 0,
                 hessian: bool = False, clock: FlowStepClock | None = None):
        self.quantile = quantile
        self.sample_rows = sample_rows
        self.hessian = hessian
        self.clock = clock
        self.layers: dict[str, ChannelStats] = {}
        self._handles = [layer.register_forward_pre_hook(self._hook_for(name)) for name, layer in layers.items()]

    def _hook_for(self, name: str):
        def hook(module: nn.Module, args: tuple) -> None:
            x = args[0]
            absmax = x.detach().abs().float().reshape(-1, x.shape[-1]).amax(dim=0)
            # without a clip quantile (smoothing only) nothing reads it: keep the magnitude
            quantile = absmax if self.quantile is None else per_call_quantile(x, self.quantile)
            seen = self.layers.get(name)
            if seen is None:
                self.layers[name] = ChannelStats(absmax.cpu(), quantile.cpu(), 1)
            else:
                seen.absmax = torch.maximum(seen.absmax, absmax.cpu())
                seen.quantile = torch.maximum(seen.quantile, quantile.cpu())
                seen.calls += 1
            if self.sample_rows:
                self._track_rows(self.layers[name], x.detach().float().reshape(-1, x.shape[-1]))
            if self.hessian:
                rows = x.detach().float().reshape(-1, x.shape[-1])
                stats = self.layers[name]
                stats.hessian = rows.t() @ rows if stats.hessian is None else stats.hessian.addmm_(rows.t(), rows)
            if self.clock is not None and self.clock.step is not None:
                self._track_step(self.layers[name], self.clock.step, absmax.max().cpu())

        return hook

    @staticmethod
    def _track_step(stats: ChannelStats, step: int, absmax: torch.Tensor) -> None:
        seen = stats.step_absmax if stats.step_absmax is not None else torch.zeros(0)
        if step >= seen.numel():  # a step this layer has not run in before
            seen = torch.cat([seen, torch.zeros(step + 1 - seen.numel())])
        seen[step] = torch.maximum(seen[step], absmax)
        stats.step_absmax = seen

    def _track_rows(self, stats: ChannelStats, rows: torch.Tensor) -> None:
        abs_sum = rows.abs().sum(dim=0, dtype=torch.float64).cpu()
        stats.abs_sum = abs_sum if stats.abs_sum is None else stats.abs_sum + abs_sum
        stats.samples, stats.sample_stride = keep_strided_rows(
            stats.samples, stats.sample_stride, stats.rows, rows, self.sample_rows
        )
        stats.rows += rows.shape[0]

    def close(self) -> None:
        for handle in self._handles:
            handle.remove()

    def stats(self, key: str, keyed: dict) -> CalibrationStats:
        """What was observed. Hessians stay on their layers' device: `save_stats` writes them from there one
        at a time (torch.save copies each storage to the host as it writes it), so a calibration job never
        holds them all in host memory (pi0.5 e2e: 24 GiB), and `load_stats` maps them to the CPU."""
        return CalibrationStats(key=key, keyed_fields=dict(keyed), layers=dict(self.layers))


@contextlib.contextmanager
def observe(
    layers: Mapping[str, nn.Linear], quantile: float | None = 0.999, sample_rows: int = 0, hessian: bool = False,
    clock: FlowStepClock | None = None,
) -> Iterator[ActivationObserver]:
    """Observe the inputs of `layers` (qualified name -> linear) while the block runs; with
    `sample_rows` > 0 also keep mean |x| and a strided sample of input rows (AWQ, GPTQ), with
    `hessian` also X^T X (GPTQ), with a flow-step `clock` also max |x| per flow step."""
    observer = ActivationObserver(layers, quantile, sample_rows, hessian, clock)
    try:
        yield observer
    finally:
        observer.close()


def smoothing_factors(act_absmax: torch.Tensor, weight: torch.Tensor, alpha: float | None) -> torch.Tensor:
    """d_j = max(a_j^alpha / w_j^(1-alpha), 1e-5), a_j and w_j = max_i |W_ij| floored at 1e-5."""
    if alpha is None:
        raise UserError("calibration settings without a smoothing alpha (statistics for AWQ only) cannot smooth")
    a = act_absmax.float().to(weight.device).clamp_min(FLOOR)
    w = weight.detach().float().abs().amax(dim=0).clamp_min(FLOOR)
    return (a.pow(alpha) / w.pow(1.0 - alpha)).clamp_min(FLOOR)


def save_stats(stats: CalibrationStats, path: str | Path) -> Path:
    """Write statistics atomically (temp file + rename) so a killed run leaves no partial cache."""
    payload = {
        "key": stats.key,
        "keyed_fields": stats.keyed_fields,
        "layers": {n: _layer_payload(s) for n, s in stats.layers.items()},
    }
    with atomic_write(path, "wb") as handle:
        torch.save(payload, handle)
    return Path(path)


def _layer_payload(stats: ChannelStats) -> dict:
    payload = {"absmax": stats.absmax, "quantile": stats.quantile, "calls": stats.calls}
    if stats.abs_sum is not None:
        payload.update(abs_sum=stats.abs_sum, rows=stats.rows, samples=stats.samples, sample_stride=stats.sample_stride)
    if stats.hessian is not None:
        payload["hessian"] = stats.hessian
    if stats.step_absmax is not None:
        payload["step_absmax"] = stats.step_absmax
    return payload


def load_stats(path: str | Path, expected_key: str | None = None) -> CalibrationStats:
    path = Path(path)
    if not path.is_file():
        raise UserError(f"calibration statistics not found: {path}")
    # Mapped, not read: a GPTQ cell's Hessians outweigh its policy (pi0.5 e2e: 24 GiB in float32), and the method
    # reads one layer's at a time (copy-on-write pages: nothing is written back to the file).
    payload = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    if expected_key is not None and payload["key"] != expected_key:
        raise UserError(f"calibration cache {path} has key {payload['key']}, expected {expected_key}")
    layers = {n: ChannelStats(**s) for n, s in payload["layers"].items()}
    return CalibrationStats(key=payload["key"], keyed_fields=payload["keyed_fields"], layers=layers)
