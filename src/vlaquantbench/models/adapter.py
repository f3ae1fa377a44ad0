"""The adapter protocol: how the runner drives a policy, whatever its library.

An adapter loads a policy (`load`), names its component scopes (`components`, from the model
spec), starts an episode (`reset(seed)` returns the episode's own random stream) and predicts
action chunks for a batch of observations (`act`). The runner executes `executed_chunk` of the
`predicted_chunk` actions before observing again; both are recorded in every cell header, and a
cell fails if the adapter's executed length differs from the cell config (paper Sec. 5).

`model` is the module quantization walks; qualified layer names are relative to it.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import torch
from torch import nn

from vlaquantbench.config.study import RunnerConfig
from vlaquantbench.envs.registry import benchmark_of, cameras_of, get_benchmark
from vlaquantbench.errors import UserError
from vlaquantbench.models.client import adapter_conventions, client_conventions
from vlaquantbench.models.registry import adapter_class


class PolicyRun(Protocol):
    """What an adapter config is made from: a typed cell config (`cells.CellConfig`) or calibration config
    (`cells.CalibrationConfig`, whose sampler is always eager, so it names no method). Declared here rather
    than imported, as `cells` imports the model registry."""

    model: str
    variant: str
    checkpoint: str | None
    revision: str | None
    benchmark: str
    suite: str
    runner: RunnerConfig


@dataclass(frozen=True)
class AdapterConfig:
    """What an adapter needs to build its policy; filled from a canonical cell config."""

    model: str
    # "full": released checkpoint; "demo": reduced-width random weights; "random": the released
    # architecture at full size with seeded random weights (throughput benchmarks without a checkpoint)
    variant: str
    checkpoint: str | None = None
    revision: str | None = None  # the revision the cell pins (full variant)
    checkpoint_dir: str | None = None  # local snapshot of `checkpoint` (full variant)
    # The cell's benchmark: the model's adapter conventions there (`models.client.adapter_conventions`) say how its
    # observations and actions are read. None (a policy driven by hand): the registered benchmark that the
    # observation's keys fit (`envs.registry.benchmark_of`).
    benchmark: str | None = None
    suite: str | None = None  # the cell's suite (a checkpoint's statistics may be per suite)
    device: str = RunnerConfig.device
    dtype: str = RunnerConfig.dtype
    executed_chunk: int | None = RunnerConfig.executed_chunk  # None: the model's released client
    flow_steps: int = RunnerConfig.flow_steps
    seed: int = 0  # demo and random weights
    # "captured" or "eager" (`resolve_sampler`). Eager unless a cell resolves otherwise: the replay
    # and diagnostics probes wrap lerobot's `sample_actions`/`denoise_step`, which only eager calls.
    sampler: str = "eager"
    # Camera role ("main", "wrist") -> the observation key of its image: the cell's benchmark's declaration
    # (`envs.registry.Benchmark.cameras`). Adapters read cameras by role only. None (a policy driven by hand):
    # the declaration of the registered benchmark that the observation's keys fit (`envs.registry.cameras_of`).
    cameras: dict[str, str] | None = None

    @property
    def weights_ran(self) -> tuple[str, str | None]:
        """The checkpoint and revision that really run: the pinned release, or, for the demo and random
        variants, seeded random weights (their study entry's checkpoint names only the architecture they
        imitate, so records and summary rows must not name it as what ran)."""
        if self.variant == "full":
            return self.checkpoint, self.revision
        return f"random weights ({self.variant} variant of {self.model}, seed {self.seed})", None

    @classmethod
    def from_cell(cls, cfg: PolicyRun, checkpoint_dir: str | None, policy_class: type) -> "AdapterConfig":
        """The adapter config of a typed cell (or calibration) config; `policy_class` is the model's adapter class."""
        runner = cfg.runner
        return cls(
            model=cfg.model,
            variant=cfg.variant,
            checkpoint=cfg.checkpoint,
            revision=cfg.revision,
            checkpoint_dir=checkpoint_dir,
            benchmark=cfg.benchmark,
            suite=cfg.suite,
            device=runner.device,
            dtype=runner.dtype,
            executed_chunk=runner.executed_chunk,
            flow_steps=runner.flow_steps,
            sampler=resolve_sampler(cfg, policy_class),
            cameras=dict(get_benchmark(cfg.benchmark).cameras),
        )


@runtime_checkable
class PolicyAdapter(Protocol):
    config: AdapterConfig
    predicted_chunk: int
    executed_chunk: int
    model: nn.Module
    # Set by `load`: the header's `tokenizer` and `normalization` records (what the policy's
    # prompts were tokenized with and its actions unnormalized with, with file hashes).
    checkpoint_provenance: dict
    control_mode: str  # "delta" or "absolute" end-effector actions (the arm controller's mode)
    reads_images: bool  # False: the env renders no image for it
    # Glob patterns of scoped linear layers the policy never calls (their hooks cannot fire)
    idle_layers: tuple[str, ...]

    @property
    def components(self) -> dict: ...

    def load(self) -> None: ...

    def prepare_inference(self, report) -> dict:
        """Set up the configured sampler once quantization (`report`) has installed its hooks;
        returns the cell header's `inference` record."""
        ...

    def fast_path_probe(self) -> dict | None:
        """When the configured sampler is a fast path, its first chunk against the eager policy's
        on the same input (`fast_path_probe`); None for the eager sampler."""
        ...

    def reset(self, seed: int) -> torch.Generator: ...

    def act(self, observations: Sequence[dict], generators: Sequence[torch.Generator]) -> np.ndarray:
        """Action chunks `[n, predicted_chunk, action dimensions]` in environment units for n observations."""
        ...


class AdapterBase:
    """What every adapter shares: its config, the model spec's components, per-episode streams and
    the executed-chunk bounds check. Subclasses set `name` and implement `load` and `act`."""

    name: str
    supports_captured_sampler = False  # `AdapterConfig.sampler` "captured" (see `resolve_sampler`)
    control_mode = "delta"  # actions are end-effector pose deltas
    # Whether the policy reads camera images; the env renders none for one that does not (`envs.env_settings`).
    reads_images = True
    idle_layers: tuple[str, ...] = ()

    def __init__(self, config: AdapterConfig):
        self.config = config
        self.model: nn.Module | None = None
        self.predicted_chunk = 0
        if config.executed_chunk is None:  # the released client's (cells always set it)
            config = dataclasses.replace(config, executed_chunk=client_conventions(self.name).executed_chunk)
            self.config = config
        self.executed_chunk = config.executed_chunk
        self._device = torch.device(config.device)
        if config.benchmark is not None:  # refused now, before the policy loads, where its client never ran
            adapter_conventions(self.name, config.benchmark)

    def adapter_conventions(self, observation: dict):
        """The model's adapter conventions (`models.client.adapter_conventions`) on the config's benchmark, else on
        the registered benchmark that `observation`'s keys fit; None for a model that declares none."""
        return adapter_conventions(self.name, self.config.benchmark or benchmark_of(observation))

    @property
    def components(self) -> dict:
        from vlaquantbench.models.registry import get_model_spec

        return get_model_spec(self.name).components

    def prepare_inference(self, report) -> dict:
        return {"sampler": "eager"}

    def fast_path_probe(self) -> dict | None:
        return None

    def reset(self, seed: int) -> torch.Generator:
        return episode_generator(seed)

    def cameras(self, observation: dict) -> dict[str, str]:
        """Camera role -> the key of its image in `observation` (and the observations batched with it): the
        config's `cameras`, else the registered benchmark's that the observation's keys fit."""
        if self.config.cameras is not None:
            return self.config.cameras
        return cameras_of(observation)

    def camera_images(self, observations: Sequence[dict], role: str,
                      cameras: dict[str, str] | None = None) -> np.ndarray | None:
        """The images of camera `role` of every observation, stacked (n x H x W x 3, uint8), found through
        `cameras` (role -> key; default `self.cameras`); None when the observations have no camera of that role."""
        key = (cameras or self.cameras(observations[0])).get(role)
        if key is None or key not in observations[0]:
            return None
        return np.stack([obs[key] for obs in observations])

    def _start_chunk(self, observations: Sequence, generators: Sequence) -> None:
        if len(observations) != len(generators):
            raise ValueError(f"{len(observations)} observations but {len(generators)} generators")
        invariance = getattr(self, "_invariance", None)
        if invariance is not None:
            invariance.batch_size = len(observations)

    def _check_chunk(self) -> None:
        if not 0 < self.executed_chunk <= self.predicted_chunk:
            raise UserError(
                f"{self.name}: executed chunk {self.executed_chunk} must lie in 1..{self.predicted_chunk} (predicted)"
            )


def wait_for_device(device: torch.device) -> None:
    """Block until `device` has finished the work queued so far, sleeping rather than spinning.

    CUDA's default wait spins a CPU core while it waits (one process, fewer contexts than cores); in
    the closed-loop runner that core belongs to the simulator workers for the whole policy call."""
    if device.type == "cuda":
        done = torch.cuda.Event(blocking=True)
        done.record()
        done.synchronize()


def make_adapter(config: AdapterConfig) -> PolicyAdapter:
    return adapter_class(config.model)(config)


def resolve_sampler(cfg: PolicyRun, policy_class: type) -> str:
    """A cell's `runner.sampler` made concrete: "captured" or "eager".

    `auto` is the fastest path that computes the cell: the captured sampler (one CUDA graph per
    chunk, `models.pi05.fast.CapturedSampler`; benchmarks/README.md) on CUDA where the model and method allow
    it, else eager. On the CPU `auto` stays eager: there the eager path with `BatchInvariantLinears`
    is what makes an episode's actions bit-identical at batch 1 and batch 4 (the captured code
    computes per-chunk constants for all batch rows and steps in one product). The choices are
    the config schema's (`study.runner.sampler`), which validated `cfg`; UserError for an impossible
    choice, before the policy loads. `policy_class`: the model's adapter class.
    """
    from vlaquantbench.quant.methods import METHODS

    choice = cfg.runner.sampler
    if choice == "eager":  # calibration's always (`cells.calibration_config`)
        return choice
    obstacle = None
    if not policy_class.supports_captured_sampler:
        obstacle = f"model {cfg.model} has no captured sampler"
    # (cell methods outside the registry, `ablate` and `calib*`, are RTN, which can be captured)
    elif (method := METHODS.get(cfg.method)) is not None and method.uncapturable is not None:
        obstacle = f"method {cfg.method} cannot be captured ({method.uncapturable})"
    if choice == "captured":
        if obstacle:
            raise UserError(f"cell {cfg.ref}: study.runner.sampler is 'captured' but {obstacle}; use 'auto' or 'eager'")
        return choice
    return "captured" if obstacle is None and torch.device(cfg.runner.device).type == "cuda" else "eager"


# What a fast path's first chunk may differ from the eager policy's (`fast_path_probe`).
# CUDA: bf16 operation order, TF32 products in lerobot's float32 vision tower and fused kernels move
# the last bits, and a 4-bit activation rounding that flips on such a difference moves a value by a
# whole grid step, which later layers amplify. Measured for pi0.5's captured sampler at full size on
# an H200 (benchmarks/results/gpu_policy_inference_cameras*.json, `captured_vs_eager_rel_l2_b1`):
# relative L2 3.3e-4 (BASELINE), 2.4e-2 (W4A4 e2e). The bound, 0.05, leaves 2x headroom over the
# worst of them and still catches a fast path computing with stale weights (`tests/test_pi05_probe.py`:
# stale action-expert q/k/v copies are off by more than twice the bound). Random weights, not a
# checkpoint: benchmarks/gpu_policy_inference.py re-measures it.
CUDA_PROBE_BOUND = {"rel_l2": 0.05}
# CPU: the fast path runs the eager policy's float32 operations, but in other shapes (cameras in one
# batch, all flow steps' conditioning in one product, heads folded). IEEE 754 fixes the rounding of
# each operation, not the order of a sum, and the CPU kernels choose that order by shape and instruction
# set: on an AVX-512 FP16/AMX machine (an H200 host's Xeon) the captured W4A4 chunk differed by rel_l2
# 8.8e-8 (9.9e-8 with MKL pinned to its AVX2 branch, MKL_CBWR=AVX2: pinning MKL alone does not make it
# bit-equal), while this project's AVX2-path CI machines agreed bit for bit. So what the arithmetic guarantees is
# agreement up to moving intermediates by a few units in the last place (ulps), and how far that moves
# the actions depends on the cell: measured on the demo policy with every input moved by one ulp,
# rel_l2 1.3e-7 (BASELINE), 7e-8 (W4A4 ah), 4e-3 (W4A8 e2e), 7.7e-2 (W4A4 e2e: 4-bit rounding flips,
# amplified). The probe therefore measures that spread on the cell itself (`eager_ulp_spread`: the eager
# policy against itself with its float inputs moved one ulp in a seeded direction, the largest of
# `ULP_PROBES` draws) and allows `CPU_PROBE_FACTOR` times it. A fast path computing with stale weights
# is off by far more (tests/test_pi05_probe.py); a cell that happens to agree bit for bit still
# records `max_abs_diff: 0.0`.
CPU_PROBE_FACTOR = 8
ULP_PROBES = 2


def ulp_moved(x: torch.Tensor, directions: torch.Generator) -> torch.Tensor:
    """`x` with every element moved one unit in the last place, up or down as `directions` draws."""
    up = torch.randint(0, 2, x.shape, generator=directions).bool().to(x.device)
    return torch.nextafter(x, torch.where(up, torch.inf, -torch.inf).to(x.dtype))


def _rel_l2(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.double(), b.double()
    return ((a - b).norm() / b.norm().clamp_min(1e-30)).item()


def fast_path_probe(path: str, fast: torch.Tensor, eager: torch.Tensor,
                    eager_ulp_moved: Callable[[int], torch.Tensor] | None = None) -> dict:
    """The header record of a fast path's first chunk `fast` against the eager policy's `eager`.
    On the CPU `eager_ulp_moved(seed)` is the eager chunk with its float inputs moved one ulp
    (`ulp_moved`), which sets the bound (see `CPU_PROBE_FACTOR`)."""
    diffs = {"max_abs_diff": (fast.double() - eager.double()).abs().max().item(), "rel_l2": _rel_l2(fast, eager)}
    if eager.is_cuda:
        bound, spread = CUDA_PROBE_BOUND, {}
        allowed = bound["rel_l2"]
    else:
        if eager_ulp_moved is None:
            raise ValueError("a CPU fast-path probe needs the eager chunk with its inputs moved one ulp")
        spread = {"eager_ulp_spread": max(_rel_l2(eager_ulp_moved(seed), eager) for seed in range(ULP_PROBES))}
        bound = {"rel_l2": f"{CPU_PROBE_FACTOR} x eager_ulp_spread"}
        allowed = CPU_PROBE_FACTOR * spread["eager_ulp_spread"]
    return {"path": path, "device": eager.device.type, **diffs, **spread, "bound": bound,
            "passed": bool(torch.isfinite(fast).all()) and diffs["rel_l2"] <= allowed}


def episode_generator(seed: int, device: str | torch.device = "cpu") -> torch.Generator:
    """An episode's random stream: every draw of the episode (flow noise) comes from it, so its
    actions do not depend on which other episodes share its batch."""
    return torch.Generator(device=device).manual_seed(int(seed))


class BatchInvariantLinears:
    """Computes every linear layer of a model one batch element at a time.

    CPU GEMM kernels pick their blocking from the row count, so a row's result can differ in the
    last bits between batch sizes (e.g. the `(batch, width)` time-MLP and adaRMS inputs). Running
    each element's rows separately gives every episode the same kernel shapes at any batch size, so
    its actions are bit-identical whether it ran alone or beside others. Inputs are split along the
    first dimension into `batch_size` equal parts (which also covers inputs flattened to
    `(batch * tokens, width)`). Registered hooks (quantization, calibration) still run: only
    `forward` itself is replaced.
    """

    def __init__(self, model: nn.Module):
        self.batch_size = 1
        self.layers = 0
        for module in model.modules():
            if isinstance(module, nn.Linear):
                module.forward = functools.partial(self._linear, module)
                self.layers += 1

    def _linear(self, layer: nn.Linear, x: torch.Tensor) -> torch.Tensor:
        n = self.batch_size
        if n == 1 or x.dim() < 2 or x.shape[0] % n:
            return torch.nn.functional.linear(x, layer.weight, layer.bias)
        return torch.cat([torch.nn.functional.linear(part, layer.weight, layer.bias) for part in x.chunk(n)])
