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

import torch
from torch import nn

from vlaquantbench.errors import UserError

FLOOR = 1e-5
QUANTILE_MAX_ELEMENTS = 2**24  # torch.quantile's input limit


@dataclass(frozen=True)
class CalibrationSettings:
    """Smoothing strength, clip quantile (None: smooth without clipping, an exact identity
    before quantization) and the components whose layers are smoothed and clipped."""

    alpha: float = 0.5
    quantile: float | None = 0.999
    components: tuple[str, ...] = ("ah",)


@dataclass
class ChannelStats:
    absmax: torch.Tensor  # [in_features], running max |a_j|
    quantile: torch.Tensor  # [in_features], max over calls of the per-call quantile of |a_j|
    calls: int = 0


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
        "alpha": float(settings.alpha),
        "quantile": settings.quantile,
        "components": sorted(settings.components),
        "code_revision": code_revision,
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


class ActivationObserver:
    """Forward pre-hooks collecting `ChannelStats` on linear inputs; use through `observe`."""

    def __init__(self, layers: Mapping[str, nn.Linear], quantile: float | None):
        self.quantile = quantile
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

        return hook

    def close(self) -> None:
        for handle in self._handles:
            handle.remove()

    def stats(self, key: str, keyed: dict) -> CalibrationStats:
        return CalibrationStats(key=key, keyed_fields=dict(keyed), layers=dict(self.layers))


@contextlib.contextmanager
def observe(layers: Mapping[str, nn.Linear], quantile: float | None = 0.999) -> Iterator[ActivationObserver]:
    """Observe the inputs of `layers` (qualified name -> linear) while the block runs."""
    observer = ActivationObserver(layers, quantile)
    try:
        yield observer
    finally:
        observer.close()


def smoothing_factors(act_absmax: torch.Tensor, weight: torch.Tensor, alpha: float) -> torch.Tensor:
    """d_j = max(a_j^alpha / w_j^(1-alpha), 1e-5), a_j and w_j = max_i |W_ij| floored at 1e-5."""
    a = act_absmax.float().to(weight.device).clamp_min(FLOOR)
    w = weight.detach().float().abs().amax(dim=0).clamp_min(FLOOR)
    return (a.pow(alpha) / w.pow(1.0 - alpha)).clamp_min(FLOOR)


def save_stats(stats: CalibrationStats, path: str | Path) -> Path:
    """Write statistics atomically (temp file + rename) so a killed run leaves no partial cache."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "key": stats.key,
        "keyed_fields": stats.keyed_fields,
        "layers": {n: {"absmax": s.absmax, "quantile": s.quantile, "calls": s.calls} for n, s in stats.layers.items()},
    }
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)
    return path


def load_stats(path: str | Path, expected_key: str | None = None) -> CalibrationStats:
    path = Path(path)
    if not path.is_file():
        raise UserError(f"calibration statistics not found: {path}")
    payload = torch.load(path, map_location="cpu", weights_only=True)
    if expected_key is not None and payload["key"] != expected_key:
        raise UserError(f"calibration cache {path} has key {payload['key']}, expected {expected_key}")
    layers = {n: ChannelStats(s["absmax"], s["quantile"], s["calls"]) for n, s in payload["layers"].items()}
    return CalibrationStats(key=payload["key"], keyed_fields=payload["keyed_fields"], layers=layers)
