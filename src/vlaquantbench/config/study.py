"""The typed study config: the `study` section of a workflow config, after schema validation.

These dataclasses are the one place where study defaults live; the schema
(`schemas/config.schema.yaml`) only says what is allowed. Everything except `label`, `tables_dir`,
`execution` and `allocations` enters each cell's canonical config (`vlaquantbench.cells.CellConfig`);
`allocations` (named allocations, `alloc-<name>` cells) enters only as the cell a name stands for.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

from vlaquantbench.config import validate
from vlaquantbench.errors import UserError
from vlaquantbench.sequential import DEFAULT_ALPHA, DEFAULT_MARGIN_PP


@dataclass(frozen=True)
class ModelWeights:
    """Which weights a model's cells use: `full` (the released checkpoint), `demo` (reduced-width random
    weights of the same classes) or `random` (the released architecture with seeded random weights)."""

    variant: str
    checkpoint: str | None = None
    revision: str | None = None  # pinned commit of the checkpoint (40 hex digits)
    # A checkpoint trained here (rule train_policy): its HF_HOME folder, whose training.json names the
    # checkpoint and revision (`models.trained_home`, resolved into each cell config when the DAG is built)
    trained: str | None = None
    # This model's own settings over the study's (values that differ from its released client's
    # conventions, `models.client`, are recorded as overrides in each cell)
    episodes_per_task: int | None = None
    runner: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class RunnerConfig:
    """The policy's runner options that change what an episode does, hence hashed into every cell. The env
    settings a config gives beside them (under the same `study.runner`) are each benchmark's own, declared by its
    settings dataclass (`envs.registry.Benchmark.settings`) with their defaults: `StudyConfig.env_settings`."""

    device: str = "cpu"
    dtype: str = "float32"
    # None: the model's released client (`models.client`): pi 10 of 50, OpenVLA-OFT 8 of 8, X-VLA 30 of 30
    executed_chunk: int | None = None
    flow_steps: int = 10  # flow-matching integration steps (cell prefix steps<N> overrides)
    max_steps: int | None = None  # None: the model's step limit on the suite, resolved into the cell config (cells)
    # auto | captured | eager (`models.adapter.resolve_sampler`); hashed because the captured and
    # eager samplers order floating-point operations differently, so actions can differ in the last bits.
    sampler: str = "auto"

    @staticmethod
    def split(runner: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
        """A config's runner section as (its runner options, its env settings): a key that is no runner option is
        an env setting, checked against each cell's benchmark's declaration when its cell is built."""
        return ({k: v for k, v in runner.items() if k in RUNNER_OPTIONS},
                {k: v for k, v in runner.items() if k not in RUNNER_OPTIONS})


# The policy's runner options: every other key of a runner section is an env setting.
RUNNER_OPTIONS = frozenset(f.name for f in fields(RunnerConfig))

@dataclass(frozen=True)
class CalibrationProtocol:
    """How calibration episodes are drawn (paper app:calib): `episodes` init states from
    `first_init_state` (+2k for calib_set<k>) of the first `tasks` tasks; smoothing `alpha` and clip
    `quantile` unless the cell name overrides alpha."""

    episodes: int = 2
    first_init_state: int = 20
    tasks: int | tuple[int, ...] = 1  # a count (tasks 0..N-1) or task ids (a study on some of a suite's tasks)
    alpha: float = 0.5
    quantile: float = 0.999
    # Every quantized cell without a smoothing calibration also collects sampled input rows, so its header
    # reports each component's `mean_rel_mse` (RTN and rotation cells need no statistics to quantize).
    layer_errors: bool = False


@dataclass(frozen=True)
class SequentialConfig:
    """The stopping rule live (issue 32, `vlaquantbench.runner.stopping`): every cell of a model but the
    `against` cell (a cell name of the same benchmark, suite and model) stops once the anytime-valid test
    of its success rate against that cell's records decides, at level `alpha` and not-worse margin
    `margin_pp`; the cap is the cell's episodes_per_task. Hashed: a stopped cell's records differ."""

    alpha: float = DEFAULT_ALPHA
    margin_pp: float = DEFAULT_MARGIN_PP
    against: str = "rtn-BASELINE-e2e"


@dataclass(frozen=True)
class ExecutionConfig:
    """How cells run, not what they compute: never hashed, so changing it reruns nothing."""

    num_envs: int = 2  # simulator worker processes per rollout job
    torch_threads: int | None = 1
    progress: bool = True  # a tqdm bar per cell
    # `interleaved`: round-robin over tasks (round k is episode k of every task), so every prefix of whole
    # rounds is balanced over tasks, as the sequential stopping rule reads it (vlaquantbench.sequential).
    # Records are the same either way: an episode's outcome depends on its (task, episode, seed) alone.
    episode_order: str = "task_major"
    # GPUs of a local node that rollout and calibrate jobs take one each (vlaquantbench.runner.gpus): None,
    # every device `nvidia-smi -L` lists; N, the first N (or devices 0..N-1 where nvidia-smi is missing, up to
    # the node's /dev/nvidia<N> files; VQB_TRUST_GPUS=1 takes N on trust).
    gpus: int | None = None
    # Rollout and calibrate jobs sharing one of those GPUs at once, each with its share of the node's cores: a
    # policy of a few million parameters leaves its device idle while its simulators step, and a short cell
    # (one the stopping rule decides in a few rounds) is mostly start-up, which the others' rollouts then fill.
    jobs_per_gpu: int = 1

    def as_kwargs(self) -> dict[str, Any]:
        """What a rollout job takes (the node's GPUs are the workflow's business, not the cell's)."""
        return {k: v for k, v in asdict(self).items() if k not in ("gpus", "jobs_per_gpu")}

    def calibration_kwargs(self) -> dict[str, Any]:
        """What a calibration job takes: it runs its fixed held-out episodes, in no cell's order."""
        return {k: v for k, v in self.as_kwargs().items() if k != "episode_order"}


@dataclass(frozen=True)
class StudyConfig:
    models: dict[str, ModelWeights] = field(default_factory=dict)
    tasks: int | tuple[int, ...] = 10  # a count (tasks 0..N-1) or task ids
    # episode i of a task starts from init state i; None: the model's client (20, X-VLA 19)
    episodes_per_task: int | None = None
    seed: int = 0  # run seed s: episode e of task t has seed 1009*t + e + 1000003*s (envs.episodes.episode_seed)
    runner: RunnerConfig = field(default_factory=RunnerConfig)
    calibration: CalibrationProtocol = field(default_factory=CalibrationProtocol)
    execution: ExecutionConfig = field(default_factory=ExecutionConfig)
    sequential: SequentialConfig | None = None  # None: every cell runs all its episodes
    label: str | None = None
    tables_dir: str | None = None
    # name -> the cell name a cell `[seed<N>-][steps<N>-]alloc-<name>` stands for (`cells.resolve_allocation`)
    allocations: dict[str, str] = field(default_factory=dict)
    # The env settings `study.runner` gives (its keys that are no runner option): each cell takes them as its
    # benchmark's declared settings, and refuses one its benchmark does not declare (`cells.CellConfig.from_ref`).
    # Derived from study.runner, not a config key of its own.
    env_settings: dict[str, Any] = field(default_factory=dict, metadata={"derived": "study.runner's env settings"})

    @classmethod
    def from_dict(cls, raw: dict[str, Any] | None, where: str = "study") -> StudyConfig:
        """The study of a config's `study` section; UserError `<where>: study.<field>: ...` first."""
        raw = dict(raw or {})
        validate(raw, "config", where, subschema=("study",))
        tasks = raw.pop("tasks", cls.tasks)
        sequential = raw.pop("sequential", None)
        runner, env_settings = RunnerConfig.split(raw.pop("runner", {}))
        _check_runner_keys(env_settings, "study.runner", where)
        models = raw.pop("models", {})
        for name, weights in models.items():
            _check_runner_keys(RunnerConfig.split(weights.get("runner", {}))[1], f"study.models.{name}.runner", where)
        return cls(
            models={name: ModelWeights(**weights) for name, weights in models.items()},
            tasks=tasks if isinstance(tasks, int) else tuple(sorted(set(tasks))),
            runner=RunnerConfig(**runner),
            env_settings=env_settings,
            calibration=_calibration_protocol(raw.pop("calibration", {})),
            execution=ExecutionConfig(**raw.pop("execution", {})),
            sequential=None if sequential is None else SequentialConfig(**sequential),
            **raw,
        )

    @property
    def task_ids(self) -> list[int]:
        return list(range(self.tasks)) if isinstance(self.tasks, int) else list(self.tasks)



def _check_runner_keys(settings: dict[str, Any], field: str, where: str) -> None:
    """A runner section's keys beyond the runner options are env settings of some registered benchmark (which
    cells take one is checked when each is built): a key none declares, a misspelt one, is refused now, naming it and
    the allowed keys, as the schema names a misspelt key of a closed section (it cannot list the settings of
    benchmarks registered from outside the package)."""
    from vlaquantbench.envs.registry import BENCHMARK_SUITES, get_benchmark

    declared = {name: get_benchmark(name).setting_names for name in BENCHMARK_SUITES}
    unknown = [key for key in settings if not any(key in names for names in declared.values())]
    if unknown:
        raise UserError(f"{where}: {field}: unknown key {', '.join(map(repr, unknown))}; allowed keys: "
                        f"{', '.join(sorted(RUNNER_OPTIONS))}, and a benchmark's env settings ("
                        + "; ".join(f"{name}: {', '.join(names)}" for name, names in declared.items()) + ")")


def _calibration_protocol(raw: dict[str, Any]) -> CalibrationProtocol:
    tasks = raw.get("tasks", CalibrationProtocol.tasks)
    return CalibrationProtocol(**{**raw, "tasks": tasks if isinstance(tasks, int) else tuple(sorted(set(tasks)))})
