"""Cell references in the authors' naming -> typed, canonical cell configs and their hashes.

A cell reference is `<benchmark>/<suite>/<model>/<cell>`; the cell name follows the grammar

    [seed<N>-][steps<N>-]<method>-<preset>-<scope>[-<subset>]

    method  a registered quantization method (`quant.methods`: rtn, gptq, gptq_act, awq, nf4, int8, int4wo,
            smoothquant, fp8, fp8_tensor, fp8_static, ...) | ablate (RTN on a named subset)
            | calib[_<comps>][_a<alpha*100>] | calib_set<k>_<comps>[_a<alpha*100>] (RTN after
            rollout smoothing and clipping)
    comps   ah | llm | ve | all   (all = every component of the scope)
    scope   ve | mp | llm | ah | e2e | ve_mp_llm
    subset  a named subset of `config/scopes.yaml` for this model (its only/exclude patterns)

A named allocation stands for a cell name: `[seed<N>-][steps<N>-]alloc-<name>` is the cell
`study.allocations[<name>]` (`[steps<N>-]<method>-<preset>-<scope>[-<subset>]`, e.g. the one the precision search
chose, `tables/search_chosen.yaml`) after the same prefixes: the same canonical config but for its names (`ref`,
`cell`), so the same config hash, folder and records (`resolve_allocation`).

`seed<N>` adds N to the study's run seed (an evaluation-seed repeat, `envs.episodes.episode_seed`);
`steps<N>` sets the number of flow-matching integration steps. `calib_set<k>` collects calibration statistics on init states
`first + 2k, first + 2k + 1` (the paper's disjoint calibration sets). Methods that need statistics
(`MethodConfig.statistics`: AWQ's sampled input rows, GPTQ's Hessians, FP8 static scales, per-flow-step
scales, SmoothQuant's migration; `MethodConfig.calibration_fields` says what the cell's calibration records) collect
them in the same calibration episodes of every component of the scope, without clipping, and
without rollout smoothing unless the method's statistics name its alpha (`smoothquant`: 0.85, the
paper's LLM deployment setting, from the input absmax of these episodes: the paper's 512 text
calibration samples cannot be drawn offline; the header's format says which). A method needing
statistics the calibration cannot collect is refused here, naming it.

`CellConfig` holds everything that changes an episode's outcome; its canonical JSON is hashed
(`config_hash`) and names the cell's output folder, so two cells share a folder exactly when they
would produce the same records. Its env settings are its benchmark's declared settings dataclass
(`envs.registry.Benchmark.settings`), filled from the config's runner sections where they set them, else its model's
client, else the declared defaults (`envs.benchmark_settings`): a setting the env never reads cannot split two cells'
folders, and a benchmark's new setting needs no change here. The canonical form keeps them in `runner`, beside the
policy's options, so that hashes stay those of cells recorded before the two were typed apart (`cell_runner`). Every field is checked against the registries (benchmarks and
suites, models, presets, methods, subsets, and the subset patterns against the model's committed
layer-name index) before any work starts, and without importing torch: the workflow builds the DAG
from these configs.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
from dataclasses import asdict, dataclass, field
from typing import Any

from vlaquantbench.config import validate
from vlaquantbench.config.study import RUNNER_OPTIONS, RunnerConfig, StudyConfig
from vlaquantbench.envs import BENCHMARK_SUITES, benchmark_settings, check_ids, check_settings, check_step_limit
from vlaquantbench.envs.registry import get_benchmark
from vlaquantbench.envs.episodes import RUN_SEED_STRIDE
from vlaquantbench.errors import UserError
from vlaquantbench.models.client import ClientConventions, adapter_conventions, client_conventions, step_limit
from vlaquantbench.models.registry import COMPONENT_NAMES, model_package, rollout_models
from vlaquantbench.models.trained_home import trained_weights
from vlaquantbench.quant.methods import METHODS, SAMPLE_ROWS, registered_methods
from vlaquantbench.quant.presets import parse_preset
from vlaquantbench.quant.patterns import scope_components
from vlaquantbench.quant.semantics import QUANT_SEMANTICS

SCOPES = ("ve", "mp", "llm", "ah", "e2e", "ve_mp_llm")
# Cell methods that are RTN grids in the quantizer: ablate = RTN on a named subset, calib* = RTN after
# rollout smoothing/clipping; every other method names a registered quantization method.
RTN_ALIASES = ("ablate",)
CALIBRATION_COMPONENTS = ("ah", "llm", "ve", "all")


def quantizer_method(cell_method: str) -> str:
    """The quantization method (`vlaquantbench.quant.methods` name) a cell's method runs."""
    return "rtn" if cell_method in RTN_ALIASES or cell_method.startswith("calib") else cell_method


_CELL_NAME = re.compile(
    r"^(?:seed(?P<seed>\d+)-)?(?:steps(?P<steps>\d+)-)?"
    r"(?P<method>[a-z0-9_]+)-(?P<preset>[A-Z][A-Z0-9]*)-(?P<scope>ve_mp_llm|e2e|ve|mp|llm|ah)"
    r"(?:-(?P<subset>[a-z0-9_]+))?$"
)
_CALIB_METHOD = re.compile(
    r"^calib(?:_set(?P<set>\d+))?(?:_(?P<comps>ah|llm|ve|all))?(?:_a(?P<alpha>\d+))?$"
)


_ALLOCATION = re.compile(r"^(?P<seed>seed\d+-)?(?P<steps>steps\d+-)?alloc-(?P<name>[a-z0-9_]+)$")


def resolve_allocation(name: str, allocations: dict[str, str], ref: str | None = None) -> str:
    """The cell name `name` stands for: itself, or for `[seed<N>-][steps<N>-]alloc-<allocation>` the cell name
    `allocations[<allocation>]` (a study's `study.allocations`) after the same prefixes. UserError naming the
    allocation and where allocations are defined when it is not one, or when both set the flow steps."""
    match = _ALLOCATION.match(name)
    if match is None:
        return name
    cell, allocation = ref or name, match["name"]
    if allocation not in allocations:
        raise UserError(f"cell {cell!r}: unknown allocation {allocation!r}: study.allocations defines "
                        f"{', '.join(sorted(allocations)) or 'none'} (the precision search writes the one it chose to "
                        "tables/search_chosen.yaml, a config to add after the study's with --configfile)")
    spelled = allocations[allocation]
    if match["steps"] and spelled.startswith("steps"):
        raise UserError(f"cell {cell!r}: allocation {allocation!r} is {spelled}, which sets the flow steps already: "
                        "drop the cell's steps<N>- prefix")
    if _ALLOCATION.match(spelled) or spelled.startswith("seed"):
        raise UserError(f"cell {cell!r}: study.allocations.{allocation} is {spelled!r}: an allocation names a cell "
                        "[steps<N>-]<method>-<preset>-<scope>[-<subset>], not another allocation or a run seed")
    return f"{match['seed'] or ''}{match['steps'] or ''}{spelled}"


def parse_cell_name(name: str, ref: str | None = None) -> dict[str, Any]:
    """Split a cell name into its fields; UserError naming the cell (its reference `ref` when given)
    and the grammar on a mismatch."""
    cell = ref or name
    match = _CELL_NAME.match(name)
    if not match and _ALLOCATION.match(name):
        raise UserError(f"cell {cell!r}: {name!r} names an allocation of study.allocations, which only a study's "
                        "cells resolve (here no study is known): name the cell it stands for")
    if not match:
        raise UserError(
            f"cell {cell!r}: name {name!r} does not follow "
            "[seed<N>-][steps<N>-]<method>-<preset>-<scope>[-<subset>] "
            f"(scope one of {', '.join(SCOPES)})"
        )
    fields = match.groupdict()
    method = fields["method"]
    calibration = None
    if method.startswith("calib"):
        calib = _CALIB_METHOD.match(method)
        if not calib:
            raise UserError(
                f"cell {cell!r}: method {method!r} is not calib[_set<k>][_<{'|'.join(CALIBRATION_COMPONENTS)}>][_a<alpha*100>]"
            )
        calibration = {
            "set": int(calib["set"]) if calib["set"] is not None else None,
            "components": calib["comps"] or "all",
            "alpha": int(calib["alpha"]) / 100 if calib["alpha"] is not None else None,
        }
    elif method not in RTN_ALIASES and method not in METHODS:
        raise UserError(
            f"cell {cell!r}: unknown method {method!r}; expected one of "
            f"{', '.join(registered_methods() + list(RTN_ALIASES))} or calib[_set<k>]_<comps>[_a<alpha*100>]"
        )
    return {
        "seed_offset": int(fields["seed"] or 0),
        "flow_steps": int(fields["steps"]) if fields["steps"] is not None else None,
        "method": method,
        "preset": fields["preset"],
        "scope": fields["scope"],
        "subset": fields["subset"],
        "calibration": calibration,
    }


def parse_ref(ref: str) -> tuple[str, str, str, str]:
    parts = ref.strip("/").split("/")
    if len(parts) != 4 or not all(parts):
        raise UserError(f"cell reference {ref!r} is not <benchmark>/<suite>/<model>/<cell>")
    return parts[0], parts[1], parts[2], parts[3]


@dataclass(frozen=True)
class CellCalibration:
    """What a cell's calibration episodes observe (`components`), where (tasks x init states, seed),
    and what the quantizer does with it (smoothing `alpha`, clip `quantile`; None: neither)."""

    components: tuple[str, ...]
    alpha: float | None
    quantile: float | None
    tasks: tuple[int, ...]
    init_states: tuple[int, ...]
    seed: int
    sample_rows: int | None = None  # AWQ's and GPTQ's sampled input rows per layer; absent from the canonical form when None
    hessian: bool | None = None  # GPTQ's X^T X per layer; absent from the canonical form when None
    step_scales: bool | None = None  # max |x| per flow step per layer (step_static); absent when None

    @classmethod
    def from_dict(cls, calibration: dict[str, Any]) -> CellCalibration:
        return cls(**{**calibration, **{k: tuple(calibration[k]) for k in ("components", "tasks", "init_states")}})


@dataclass(frozen=True)
class AgainstCell:
    """The cell a sequential cell is tested against: its reference and config hash (the rollout reads its records)."""

    ref: str
    config_hash: str


@dataclass(frozen=True)
class SequentialSpec:
    """A cell's stopping rule under study.sequential (`runner.stopping`): level `alpha`, not-worse margin
    `margin_pp`, and the cell it is tested against. Its level, margin and the against cell's name satisfy the
    rules of `study.sequential` in the config schema, checked when it is built or read back."""

    alpha: float
    margin_pp: float
    against: AgainstCell

    def __post_init__(self):
        validate({"alpha": self.alpha, "margin_pp": self.margin_pp, "against": parse_ref(self.against.ref)[3]},
                 "config", f"cell sequential spec against {self.against.ref!r}", subschema=("study", "sequential"))

    @classmethod
    def from_dict(cls, raw: dict[str, Any]) -> SequentialSpec:
        return cls(alpha=raw["alpha"], margin_pp=raw["margin_pp"], against=AgainstCell(**raw["against"]))


@dataclass(frozen=True)
class Override:
    """A cell value that differs from its model's released client: the client's and the cell's."""

    client: Any
    cell: Any


@dataclass(frozen=True)
class CellOverrides:
    """The values of a cell that differ from its model's released client conventions (`models.client`): each of
    the client's runner options and env settings (`ClientConventions.runner`), its episodes per task and its step
    limit; None where the cell keeps the client's (absent from the canonical form, which is what `as_dict` gives and
    what the hash covers). Each value satisfies the config schema's rule of the field it stands for, checked when it
    is built or read back."""

    executed_chunk: Override | None = None
    control_mode: Override | None = None
    mujoco: Override | None = None
    episodes_per_task: Override | None = None
    max_steps: Override | None = None

    def __post_init__(self):
        for key, override in self.given().items():
            if not isinstance(override, Override) or override.client == override.cell:
                raise UserError(f"cell overrides: {key}: {override!r} is not a value that differs from the client's")
            for side in ("client", "cell"):
                where = f"cell overrides: {key}.{side}"
                if key == "episodes_per_task":
                    validate(getattr(override, side), "config", where, subschema=("study", "episodes_per_task"))
                else:  # a runner option, or an env setting (any scalar: its benchmark's declaration checks it)
                    validate({key: getattr(override, side)}, "config", where, subschema=("study", "runner"))

    def given(self) -> dict[str, Override]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if getattr(self, f.name) is not None}

    def as_dict(self) -> dict[str, dict[str, Any]]:
        """The canonical form: {key: {client, cell}} of the values that differ."""
        return {key: asdict(override) for key, override in self.given().items()}

    @classmethod
    def from_dict(cls, raw: dict[str, dict[str, Any]], where: str) -> CellOverrides:
        known = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(raw) - set(known))
        if unknown:
            raise UserError(f"{where}: overrides: {', '.join(unknown)} is not a value a client sets ({', '.join(known)})")
        return cls(**{key: Override(**value) for key, value in raw.items()})


@dataclass(frozen=True)
class PolicyRunConfig:
    """What a cell and its calibration episodes share: where they run and the policy's weights."""

    benchmark: str
    suite: str
    model: str
    variant: str
    checkpoint: str | None
    revision: str | None


@dataclass(frozen=True)
class CellConfig(PolicyRunConfig):
    """One cell: everything that changes its episodes. `to_dict()` is its canonical form (hashed,
    written to its header, passed to the runner); `from_dict` reads it back."""

    ref: str
    cell: str
    method: str
    preset: str
    scope: str
    subset: str | None
    only: tuple[str, ...] | None
    exclude: tuple[str, ...] | None
    calibration: CellCalibration | None
    seed: int
    tasks: tuple[int, ...]
    episodes_per_task: int
    # Its benchmark's env settings: an instance of the settings dataclass the benchmark declares.
    env: Any
    runner: RunnerConfig = field(default_factory=RunnerConfig)
    # The model's released client conventions (`models.client`) and every value of this cell that
    # differs from them: recorded, never silent.
    client: ClientConventions | None = None
    overrides: CellOverrides = field(default_factory=CellOverrides)
    # study.sequential's stopping rule and the cell it is tested against ({ref, config_hash}, whose records
    # the rollout reads); None (absent from the canonical form, so fixed-design hashes are unchanged) for
    # a fixed-design cell and for the `against` cell itself.
    sequential: SequentialSpec | None = None

    @classmethod
    def from_ref(cls, ref: str, study: StudyConfig) -> CellConfig:
        """The cell `ref` under `study`; UserError naming the reference and the bad field first."""
        benchmark, suite, model, name = parse_ref(ref)
        spelled = resolve_allocation(name, study.allocations, ref)  # a named allocation: the cell it stands for
        fields = parse_cell_name(spelled, ref)
        _check_registries(ref, benchmark, suite, model, fields["preset"], quantizer_method(fields["method"]))
        if model not in study.models:
            raise UserError(f"cell {ref!r}: model {model!r} is not in study.models ({', '.join(study.models) or 'none'})")
        _check_settings(ref, benchmark, model, study)  # as the config gives them, before a trained checkpoint's own
        weights = study.models[model]
        if weights.trained is not None:  # checkpoint, revision, input size and chunk from its training.json
            weights = trained_weights(model, weights)
        client = client_conventions(model, benchmark)
        try:  # the model's step limit on this suite, resolved now: hashed with the cell
            released_limit = step_limit(model, benchmark, suite)
            adapter_conventions(model, benchmark)  # refused now where its client never ran there (not hashed)
        except UserError as err:
            raise UserError(f"cell {ref!r}: {err}") from None
        runner, env = _runner(ref, benchmark, model, study, weights.runner, client, fields["flow_steps"], released_limit)
        episodes, _ = episodes_per_task(study, model, benchmark)
        only, exclude = _subset_patterns(ref, model, fields["scope"], fields["subset"])
        seed = study.seed + fields["seed_offset"]
        calibration = _calibration(ref, fields, study, seed)
        _check_fits_suite(ref, benchmark, suite, model, study, episodes, calibration, fields)
        _check_mujoco(ref, benchmark, model, study, client, env)
        _check_steps(ref, benchmark, suite, model, study, runner, env)
        return cls(
            ref=ref,
            cell=name,
            benchmark=benchmark,
            suite=suite,
            model=model,
            variant=weights.variant,
            checkpoint=weights.checkpoint,
            revision=weights.revision,
            method=fields["method"],
            preset=fields["preset"],
            scope=fields["scope"],
            subset=fields["subset"],
            only=only,
            exclude=exclude,
            calibration=calibration,
            seed=seed,
            tasks=tuple(study.task_ids),
            episodes_per_task=episodes,
            env=env,
            runner=runner,
            client=client,
            overrides=_overrides(client, runner, env, episodes, released_limit),
            sequential=_sequential(ref, benchmark, suite, model, spelled, study, seed),
        )

    def __post_init__(self):
        declared = get_benchmark(self.benchmark).settings
        if not isinstance(self.env, declared):
            raise UserError(f"cell {self.ref!r}: env settings {self.env!r} are not {self.benchmark}'s ({declared.__name__})")

    def to_dict(self) -> dict[str, Any]:
        cfg = asdict(self)
        for optional in ("sample_rows", "hessian", "step_scales"):  # the canonical forms (and hashes) of older cells stay
            if cfg["calibration"] is not None and cfg["calibration"][optional] is None:
                del cfg["calibration"][optional]
        if cfg["sequential"] is None:
            del cfg["sequential"]
        cfg["runner"] = {**cfg["runner"], **cfg.pop("env")}  # one section, as cells have always been hashed
        cfg["overrides"] = self.overrides.as_dict()
        return canonical(cfg)

    @classmethod
    def from_dict(cls, cfg: dict[str, Any]) -> CellConfig:
        def tuple_or_none(value):
            return None if value is None else tuple(value)

        calibration = None if cfg["calibration"] is None else CellCalibration.from_dict(cfg["calibration"])
        sequential = cfg.get("sequential")
        where = f"cell {cfg['ref']!r}"
        runner, env = cell_runner(where, cfg["benchmark"], cfg["runner"])
        return cls(**{**cfg, "only": tuple_or_none(cfg["only"]), "exclude": tuple_or_none(cfg["exclude"]),
                      "tasks": tuple(cfg["tasks"]), "calibration": calibration, "runner": runner, "env": env,
                      "client": ClientConventions(**cfg["client"]),
                      "overrides": CellOverrides.from_dict(cfg["overrides"], where),
                      "sequential": None if sequential is None else SequentialSpec.from_dict(sequential)})

    def under_current_client(self) -> CellConfig:
        """This cell with its model's client conventions on its benchmark as `models.client` declares them now, and
        its overrides taken against them; what runs (runner, episodes) is unchanged, so its records stay its own."""
        client = client_conventions(self.model, self.benchmark)
        released_limit = step_limit(self.model, self.benchmark, self.suite)
        return dataclasses.replace(self, client=client, overrides=_overrides(client, self.runner, self.env,
                                                                              self.episodes_per_task, released_limit))

    @property
    def config_hash(self) -> str:
        return config_hash(self.to_dict())

    @property
    def name(self) -> str:
        """How messages name the cell: its reference."""
        return self.ref


@dataclass(frozen=True)
class CalibrationConfig(PolicyRunConfig):
    """What a cell's calibration statistics depend on (`calibration_config`: its canonical form, hashed into the
    statistics' file name); the rollout calibration job reads it back with `from_dict`."""

    calibration: CellCalibration
    runner: RunnerConfig
    env: Any  # its benchmark's env settings, as its cells' (`CellConfig.env`)

    @classmethod
    def from_dict(cls, cfg: dict[str, Any]) -> CalibrationConfig:
        runner, env = cell_runner(f"calibration of {cfg['model']}", cfg["benchmark"], cfg["runner"])
        return cls(**{**cfg, "calibration": CellCalibration.from_dict(cfg["calibration"]), "runner": runner, "env": env})

    @property
    def name(self) -> str:
        """How messages name the calibration: its model (cells of several references may share it)."""
        return self.model


def _sequential(ref: str, benchmark: str, suite: str, model: str, name: str, study: StudyConfig,
                seed: int) -> SequentialSpec | None:
    """The cell's stopping rule under study.sequential: its level, margin and the `against` cell (its
    reference and config hash: the rollout depends on that cell's records); None for the `against` cell.
    The `against` cell is of the same benchmark, suite, model and tasks; a cell of other episode seeds (another
    `seed<N>-` prefix) is refused, naming both seeds: its rounds would pair episodes of different scenes."""
    design = study.sequential
    if design is None or name == resolve_allocation(design.against, study.allocations, ref):
        return None
    against = f"{benchmark}/{suite}/{model}/{design.against}"
    try:
        against_cell = CellConfig.from_ref(against, study)
    except UserError as err:
        raise UserError(f"cell {ref!r}: study.sequential.against: {err}") from None
    if against_cell.seed != seed:
        raise UserError(f"cell {ref!r}: study.sequential.against: {design.against} runs its episodes with run seed "
                        f"{against_cell.seed}, this cell with run seed {seed}: a contrast pairs only cells of the same "
                        "episode seeds; run it without study.sequential or drop the seed prefix that differs")
    return SequentialSpec(design.alpha, design.margin_pp, AgainstCell(against, against_cell.config_hash))


def _runner(ref: str, benchmark: str, model: str, study: StudyConfig, model_runner: dict[str, Any], client,
            flow_steps: int | None, released_limit: int) -> tuple[RunnerConfig, Any]:
    """The cell's runner options and env settings: the study's runner, then the model's own settings, then the
    client's conventions (and its step limit on the cell's suite) where unset; env settings as the benchmark
    declares them (`envs.benchmark_settings`), its defaults where neither the config nor the client sets one."""
    model_options, model_env = RunnerConfig.split(model_runner)
    values = {**asdict(study.runner), **model_options}
    for key, value in {**client.runner(), "max_steps": released_limit}.items():
        if key in values and values[key] is None:
            values[key] = value
    if flow_steps is not None:
        values["flow_steps"] = flow_steps
    given = {**study.env_settings, **model_env}
    try:
        _check_declared(benchmark)
        env = benchmark_settings(benchmark, given, {name: _runner_field(study, model, benchmark, name) for name in given},
                                 conventions=client.runner())
    except UserError as err:
        raise UserError(f"cell {ref!r}: {err}") from None
    return RunnerConfig(**values), env


def _overrides(client, runner: RunnerConfig, env: Any, episodes: int, released_limit: int) -> CellOverrides:
    """The cell values that differ from the model's released client; a convention for an env setting the cell's
    benchmark does not declare is none of the cell's."""
    settings = {f.name for f in dataclasses.fields(env)}
    cell = {k: getattr(runner if k in RUNNER_OPTIONS else env, k) for k in client.runner() if k in RUNNER_OPTIONS | settings}
    cell |= {"episodes_per_task": episodes, "max_steps": runner.max_steps}
    released = {**client.runner(), "episodes_per_task": client.episodes_per_task, "max_steps": released_limit}
    return CellOverrides(**{k: Override(client=released[k], cell=cell[k]) for k in cell if cell[k] != released[k]})


def _check_declared(benchmark: str) -> None:
    """A benchmark's env settings are named apart from the policy's runner options, with which they share a config
    section and a cell's canonical `runner`: UserError naming the ones that are not."""
    clashing = [name for name in get_benchmark(benchmark).setting_names if name in RUNNER_OPTIONS]
    if clashing:
        raise UserError(f"benchmark {benchmark!r} declares env setting(s) {', '.join(clashing)}, named like runner options "
                        "(config.study.RunnerConfig), which share study.runner with them: rename them")


def cell_runner(where: str, benchmark: str, runner: dict[str, Any]) -> tuple[RunnerConfig, Any]:
    """A canonical `runner` (a cell's or a calibration's) read back: its runner options and its benchmark's env
    settings (`where` names it in errors). Settings that another registered benchmark declares are dropped: cells
    recorded before a cell carried only its benchmark's held every benchmark's (`vqb rehash` rewrites them)."""
    _check_declared(benchmark)
    options, settings = RunnerConfig.split(runner)
    declared = get_benchmark(benchmark).setting_names
    others = {name for other in BENCHMARK_SUITES for name in get_benchmark(other).setting_names} - set(declared)
    given = {name: value for name, value in settings.items() if name not in others}
    try:
        return RunnerConfig(**options), benchmark_settings(benchmark, given, {name: f"runner.{name}" for name in given})
    except UserError as err:
        raise UserError(f"{where}: {err}") from None


def _check_registries(ref: str, benchmark: str, suite: str, model: str, preset: str, method: str) -> None:
    from vlaquantbench.models.layer_index import linear_names

    if benchmark not in BENCHMARK_SUITES:
        raise UserError(f"cell {ref!r}: unknown benchmark {benchmark!r}; known: {', '.join(BENCHMARK_SUITES)}")
    if suite not in BENCHMARK_SUITES[benchmark]:
        raise UserError(f"cell {ref!r}: unknown {benchmark} suite {suite!r}; known: {', '.join(BENCHMARK_SUITES[benchmark])}")
    try:
        model_package(model)
        if model not in rollout_models():
            raise UserError(f"model {model!r} has no rollout adapter; models with one: {', '.join(rollout_models())}")
        METHODS[method].check_preset(method, parse_preset(preset))
        if not parse_preset(preset).is_baseline and not any(linear_names(model).values()):
            raise UserError(f"model {model!r} has no network to quantize: its cells are BASELINE cells only")
    except UserError as err:
        raise UserError(f"cell {ref!r}: {err}") from None


def _check_fits_suite(ref: str, benchmark: str, suite: str, model: str, study: StudyConfig, episodes: int,
                      calibration: CellCalibration | None, fields: dict[str, Any]) -> None:
    """The study's task ids, its episodes per task (episode i starts from init state i) and the cell's
    calibration episodes lie inside the suite (`envs.BENCHMARK_SUITES`: known without a simulator, so a
    bad id fails while the DAG is built, not after the checkpoint download)."""
    size = BENCHMARK_SUITES[benchmark][suite]
    try:
        if isinstance(study.tasks, int):
            if study.tasks > size.tasks:
                raise UserError(f"study.tasks: {study.tasks} tasks, but {suite} has {size.tasks} (task ids 0..{size.tasks - 1})")
        else:
            check_ids("study.tasks", study.tasks, size.tasks, f"{suite} has {size.tasks} tasks")
        if episodes > size.init_states:
            _, field = episodes_per_task(study, model, benchmark)
            raise UserError(f"{field}: {episodes} episodes per task, but {suite} has {size.init_states} official init "
                            f"states per task (episode i starts from init state i)")
        if calibration is not None:
            protocol = study.calibration
            if isinstance(protocol.tasks, int):
                if protocol.tasks > size.tasks:
                    raise UserError(f"study.calibration.tasks: {protocol.tasks} tasks, but {suite} has {size.tasks}")
            else:
                check_ids("study.calibration.tasks", protocol.tasks, size.tasks, f"{suite} has {size.tasks} tasks")
            calib_set = (fields["calibration"] or {}).get("set")
            source = (f"study.calibration.first_init_state {protocol.first_init_state}"
                      + (f" + 2 x calib_set {calib_set}" if calib_set else "") + f", study.calibration.episodes {protocol.episodes}")
            check_ids(f"calibration init states ({source})", calibration.init_states, size.init_states,
                      f"{suite} has {size.init_states} official init states per task")
    except UserError as err:
        raise UserError(f"cell {ref!r}: {err}") from None


def episodes_per_task(study: StudyConfig, model: str, benchmark: str | None = None) -> tuple[int, str]:
    """The episodes per task of `model`'s cells on `benchmark` (episode i of a task starts from init state or
    variation i) and the config field they come from: the model's own, else the study's, else its released
    client's on that benchmark (`models.client.client_conventions`)."""
    if study.models[model].episodes_per_task:
        return study.models[model].episodes_per_task, f"study.models.{model}.episodes_per_task"
    if study.episodes_per_task:
        return study.episodes_per_task, "study.episodes_per_task"
    return client_conventions(model, benchmark).episodes_per_task, f"{model}'s client episodes_per_task"


def _runner_field(study: StudyConfig, model: str, benchmark: str, key: str) -> str:
    """The config field a cell's `runner.<key>` comes from: the model's own runner, else the study's, else (unset in
    both) the model's released client, or for an env setting the client does not set its benchmark's default."""
    if key in study.models[model].runner:
        return f"study.models.{model}.runner.{key}"
    if key in study.env_settings or getattr(study.runner, key, None) is not None:
        return f"study.runner.{key}"
    if key in RUNNER_OPTIONS or key in client_conventions(model, benchmark).runner():
        return f"{model}'s client {key}"
    return f"{benchmark}'s default {key}"


def _check_settings(ref: str, benchmark: str, model: str, study: StudyConfig) -> None:
    """The env settings the config sets for this cell (`study.runner`, `study.models.<model>.runner`) are its
    benchmark's (`envs.check_settings`): one it does not declare would be silently unused, so it is refused now,
    naming the field, before any checkpoint or simulator starts."""
    given = {key: f"study.runner.{key}" for key in study.env_settings}
    given |= {key: f"study.models.{model}.runner.{key}" for key in RunnerConfig.split(study.models[model].runner)[1]}
    try:
        check_settings(benchmark, given)
    except UserError as err:
        raise UserError(f"cell {ref!r}: {err}") from None


def _check_steps(ref: str, benchmark: str, suite: str, model: str, study: StudyConfig, runner: RunnerConfig,
                 env: Any) -> None:
    """An episode's steps fit the simulator's horizon (`envs.registry.SuiteSize.horizon`): one that outruns it dies inside
    the simulator at the horizon's step, so a longer `max_steps` is refused now, naming the field. A benchmark whose
    env settles declares `settle_steps`, which count."""
    try:
        check_step_limit(_runner_field(study, model, benchmark, "max_steps"), runner.max_steps, benchmark, suite,
                         getattr(env, "settle_steps", 0), _runner_field(study, model, benchmark, "settle_steps"))
    except UserError as err:
        raise UserError(f"cell {ref!r}: {err}") from None


def _check_mujoco(ref: str, benchmark: str, model: str, study: StudyConfig, client, env: Any) -> None:
    """A model's cells run in its software environment, which installs its client's MuJoCo pin; any other
    `mujoco` setting (of a benchmark that declares one) would be refused when the simulator starts, so it is
    refused now."""
    pinned = getattr(env, "mujoco", client.mujoco)
    if pinned != client.mujoco:
        field = _runner_field(study, model, benchmark, "mujoco")
        raise UserError(f"cell {ref!r}: {field}: {pinned!r}, but {model} cells run on MuJoCo {client.mujoco}, the "
                        "pin of their software environment (vlaquantbench.software_env)")


def _subset_patterns(ref: str, model: str, scope: str, subset: str | None) -> tuple[tuple[str, ...] | None, tuple[str, ...] | None]:
    """The subset's patterns, after checking each against the model's layer-name index."""
    from vlaquantbench.models.layer_index import linear_names
    from vlaquantbench.quant.patterns import select_names
    from vlaquantbench.quant.subsets import get_subset

    only = exclude = None
    where = f"cell {ref!r}"
    names = linear_names(model)
    try:
        if not any(names.values()):  # a policy without a network: nothing to select (BASELINE cells only)
            if subset is not None:
                raise UserError(f"subset {subset!r}: {model} has no network, so no layer to select")
            return None, None
        if subset is not None:
            where += f": subset {subset!r} of {model}"
            named = get_subset(model, subset)
            if named.scope != scope:
                raise UserError(f"is defined on scope {named.scope!r}, not {scope!r}")
            only, exclude = named.only, named.exclude
        select_names(names, scope, only, exclude)
    except UserError as err:
        raise UserError(f"{where}: {err}") from None
    return only, exclude


def quantized_counts(ref: str) -> dict[str, int]:
    """Layers and weight parameters the cell `ref` quantizes: its scope and subset on the model's committed
    layer index (the architecture built on the meta device; no torch, no records). What a cell known only
    from a summary row, which has no run header, still says about its #L and Params."""
    from vlaquantbench.models.layer_index import selected_counts

    _, _, model, name = parse_ref(ref)
    fields = parse_cell_name(name, ref)
    try:
        model_package(model)
        baseline = parse_preset(fields["preset"]).is_baseline
    except UserError as err:
        raise UserError(f"cell {ref!r}: {err}") from None
    if baseline:
        return {"layers": 0, "params": 0}
    only, exclude = _subset_patterns(ref, model, fields["scope"], fields["subset"])
    counts = selected_counts(model, fields["scope"], only, exclude).values()
    return {key: sum(component[key] for component in counts) for key in ("layers", "params")}


def _calibration(ref: str, fields: dict[str, Any], study: StudyConfig, seed: int) -> CellCalibration | None:
    parsed = fields["calibration"]
    method = METHODS.get(fields["method"])
    if method is not None:
        try:
            method.check_statistics()
        except UserError as err:
            raise UserError(f"cell {ref!r}: {err}") from None
    statistics = method.calibration_fields() if method is not None else None
    protocol = study.calibration
    if protocol.layer_errors and parsed is None and not parse_preset(fields["preset"]).is_baseline:
        # Sampled input rows of every selected layer: what the header's per-component `mean_rel_mse` is measured on.
        statistics = {**(statistics or {}), "sample_rows": SAMPLE_ROWS}
    if parsed is None and statistics is None:
        return None
    first = protocol.first_init_state + 2 * ((parsed or {}).get("set") or 0)
    in_scope = scope_components(fields["scope"], COMPONENT_NAMES)
    if parsed is None:  # the method's own statistics: every component of the scope, no smoothing or clipping
        observed = {"components": in_scope, "alpha": None, "quantile": None, **statistics}
    elif parsed["components"] == "all" or parsed["components"] in in_scope:
        observed = {
            "components": in_scope if parsed["components"] == "all" else [parsed["components"]],
            "alpha": parsed["alpha"] if parsed["alpha"] is not None else protocol.alpha,
            "quantile": protocol.quantile,
        }
    else:
        raise UserError(f"cell {ref!r}: calibrates {parsed['components']!r}, which is outside scope {fields['scope']!r}")
    return CellCalibration(
        **{**observed, "components": tuple(observed["components"])},
        tasks=tuple(range(protocol.tasks)) if isinstance(protocol.tasks, int) else protocol.tasks,
        init_states=tuple(range(first, first + protocol.episodes)),
        seed=seed,
    )


def cell_config(ref: str, study: StudyConfig | dict[str, Any]) -> dict[str, Any]:
    """The canonical config of the cell `ref` under `study` (typed, or a config's raw `study` section,
    which is validated first). Raises UserError naming the reference and the bad field."""
    if not isinstance(study, StudyConfig):
        study = StudyConfig.from_dict(study)
    return CellConfig.from_ref(ref, study).to_dict()


def canonical(cfg: dict[str, Any]) -> dict[str, Any]:
    """A JSON round trip: the exact value that is hashed and written to headers."""
    return json.loads(canonical_json(cfg))


def canonical_json(cfg: dict[str, Any]) -> str:
    return json.dumps(cfg, sort_keys=True, separators=(",", ":"), ensure_ascii=True)


# A cell's names: two cells that differ only here run the same experiment (`rtn-W4A4-ah` and
# `ablate-W4A4-ah`, two subsets with the same patterns, or `alloc-<name>` and the cell it stands for) and share
# one folder and one job.
NAME_FIELDS = ("ref", "cell", "subset")


def hashed_config(cfg: dict[str, Any]) -> dict[str, Any]:
    """What a config's hash covers: everything that changes its results, i.e. the config without its
    names, with the cell method as the quantizer method it runs, the quantization-semantics version and,
    for a run seed other than 0, the episode seeds' run-seed stride."""
    kept = {k: v for k, v in cfg.items() if k not in NAME_FIELDS}
    if "method" in kept:
        kept["method"] = quantizer_method(kept["method"])
    # Run seed s used to add s to every episode seed; it now adds the authors' RUN_SEED_STRIDE * s. A cell or
    # calibration of run seed s != 0 runs other episodes than before, so it must not reuse the old folder or
    # statistics; run seed 0's episodes, and so its hash, stay.
    run_seed = cfg["seed"] if "seed" in cfg else cfg["calibration"]["seed"]
    stride = {"run_seed_stride": RUN_SEED_STRIDE} if run_seed else {}
    return {**kept, "quant_semantics": QUANT_SEMANTICS, **stride}


def config_hash(cfg: dict[str, Any]) -> str:
    """12 hex digits of the SHA-256 of the canonical JSON of `hashed_config(cfg)`."""
    return hashlib.sha256(canonical_json(hashed_config(cfg)).encode()).hexdigest()[:12]


def calibration_config(cfg: dict[str, Any]) -> dict[str, Any] | None:
    """What the calibration statistics of a cell depend on (cells sharing it share statistics).

    Statistics are collected on the unquantized policy, so the quantization preset and the
    evaluation episodes do not enter; the layers observed are the calibrated components' linears.
    """
    if cfg["calibration"] is None:
        return None
    keep = ("benchmark", "suite", "model", "variant", "checkpoint", "revision")
    # Observers are Python hooks that must run on every chunk; a captured graph would replay
    # without them, so calibration always samples eagerly, whatever the cell's sampler.
    runner = {**cfg["runner"], "sampler": "eager"}
    return canonical({**{k: cfg[k] for k in keep}, "calibration": cfg["calibration"], "runner": runner})


def checkpoint_key(cfg: dict[str, Any]) -> str:
    """File-name-safe key of a cell's weights: model, variant and revision."""
    revision = (cfg.get("revision") or "none")[:12]
    return f"{cfg['model']}-{cfg['variant']}-{revision}"


def checkpoint_request(cfg: dict[str, Any], study: StudyConfig) -> dict[str, Any]:
    """What `runner.checkpoint.download_checkpoint` takes for a cell's weights under `study`: model, variant,
    checkpoint and revision, and for a model trained here (`study.models.<model>.trained`) its folder,
    `trained_home`, which is verified instead of fetched. The DAG's checkpoint jobs and `vqb rollout` both
    ask here, so that neither resolves a trained checkpoint differently (from the hub, say)."""
    request = {k: cfg[k] for k in ("model", "variant", "checkpoint", "revision")}
    trained = study.models[cfg["model"]].trained
    return {**request, "trained_home": trained} if trained else request

