"""The benchmark registry: each benchmark package `envs/<benchmark>/` declares itself in its own light
`benchmark.py` (a `Benchmark`: its suites and their sizes, hard step limits, worker footprints, its env settings
as a typed dataclass, where its suite class, vector env class and `simulator_versions` live, and its scripted
expert if it has one) and registers it with `register_benchmark`. Nothing outside a benchmark's folder names it:
`BENCHMARK_SUITES` finds every folder's declaration the first time it is read, without importing a simulator, so
cell references, task ids and episode counts are checked while the workflow builds the DAG (`envs.memory` sizes
worker pools by the same declarations).

A benchmark package outside `envs/` (a plugin, or a test's own) is found the same way when the environment
variable `VQB_BENCHMARKS` names its declaration module (comma-separated "package.module" names, importable on
`sys.path`): every process of a run (the Snakemake workflow, its jobs, the simulator workers) inherits it."""

from __future__ import annotations

import dataclasses
import functools
import importlib
import os
import pkgutil
import threading
import types
import typing
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vlaquantbench.errors import UserError, lookup


@dataclass(frozen=True)
class Horizon:
    """A simulator's hard limit on one episode: `steps` env steps, after which it refuses to step on (it raises
    from inside the simulator, naming no setting), the settle steps after a reset included where
    `counts_settle_steps` (a benchmark whose env settles, `runner.settle_steps`)."""

    steps: int
    source: str  # where the limit is set, in words
    counts_settle_steps: bool = False


@dataclass(frozen=True)
class SuiteSize:
    tasks: int  # task ids 0..tasks-1, in the benchmark's task order
    init_states: int  # initial states or seeded task variations per task, ids 0..init_states-1
    worker_gib: float  # memory of one simulator worker process (envs.memory), measured as noted below
    # Env steps the simulator takes in one episode before it refuses another (`Horizon`): the most steps any
    # setting may ask of an episode.
    horizon: Horizon
    # Policy steps before an unfinished episode counts as a failure, whatever the model; None: each model's
    # client declares its own (`models/<model>/client.py` STEP_LIMITS).
    step_limit: int | None = None


@dataclass(frozen=True)
class ScriptedExpert:
    """A benchmark's scripted expert, and what a demonstration dataset recorded from it holds
    (`vlaquantbench.demonstrations`). The expert is the model `model` (`models/<model>/`), run through the
    closed-loop runner like any policy, on suite `suite` unless a config names another. The dataset (a lerobot
    LeRobotDataset on robot `robot_type`, `fps` frames a second) stores the main camera's image, the state and
    the action, their components named by `state_names` and `action_names` (as many as the benchmark's
    `state_dim` and `action_dim`). The suites start episodes from seeded task variations (the suite class's
    `variation_seed(task_id, variation)`), evaluation episode e from variation e, so that the demonstrations
    can take variations no evaluation starts from."""

    model: str
    suite: str
    fps: int
    robot_type: str
    state_names: tuple[str, ...]
    action_names: tuple[str, ...]


@dataclass(frozen=True)
class Benchmark:
    """A benchmark's declaration. `suite_class`, `env_class` and `simulator_versions` are "module:name" of its
    suite class (a `SuiteTasks`), its vector env class (a `WorkerVectorEnv`, whose keyword-only parameters are
    the env settings it takes) and `simulator_versions(pinned)`, imported only when a suite or env is built.
    `cameras` says what its observations show: camera role ("main", and "wrist" where there is one) -> the
    observation key of that image (beside `state` and `instruction`, which every benchmark's observation has).
    `settings` is its env settings' frozen dataclass (light: no simulator import): each field a keyword-only
    parameter of its vector env class of the same name, with the env's default, annotated with the types a config
    may give it (int, float, str, bool, None, a Literal, or a union of them), and optionally further JSON-schema rules
    in its metadata (`field(metadata={"schema": {"minimum": 0}})`). `action_dim` and `state_dim` are
    the sizes of the action its env steps with and of the `state` its observations carry (what a replay's probe
    keeps of a policy's padded chunk, and what a scripted expert's names cover). A config sets a setting under
    `study.runner` or `study.models.<model>.runner` by its name, checked against this dataclass (`settings_schema`)
    and taken only into the cells of the benchmarks that declare it (`envs.benchmark_settings`); a setting this
    benchmark does not declare is refused for its cells, naming it (`envs.check_settings`). `scripted_expert` is the expert whose
    demonstrations a policy can be trained on; None: the benchmark has none, and a config asking for its
    demonstrations is refused."""

    name: str
    suites: dict[str, SuiteSize]
    suite_class: str
    env_class: str
    simulator_versions: str
    cameras: dict[str, str]
    settings: type
    action_dim: int
    state_dim: int
    scripted_expert: ScriptedExpert | None = None

    @property
    def setting_names(self) -> tuple[str, ...]:
        """The names of the env settings it declares, in declaration order."""
        return tuple(f.name for f in dataclasses.fields(self.settings))

    @property
    def observed(self) -> tuple[str, ...]:
        """The observation keys of what a policy reads besides its instruction: each camera's image, then the state."""
        return (*self.cameras.values(), STATE)

    def resolve(self, which: str) -> Any:
        """The object `which` ("suite_class", "env_class" or "simulator_versions") names, imported now."""
        module, _, attribute = getattr(self, which).partition(":")
        return getattr(importlib.import_module(module), attribute)


# JSON-schema types of the annotations a setting may carry: what a YAML config can give.
_JSON_TYPES = {int: "integer", float: "number", str: "string", bool: "boolean", type(None): "null"}


@functools.cache
def settings_schema(settings: type, benchmark: str) -> dict[str, dict[str, Any]]:
    """Setting -> the JSON-schema rules of its values: its annotation's types (or a Literal's values) and its
    metadata's "schema" rules. A config's values are validated against these as the YAML is against its schema
    (`envs.benchmark_settings`). UserError naming the benchmark and setting for one without a default (a cell takes
    the declared default where no config sets it), of a type a config cannot give, or whose default the rules refuse."""
    from jsonschema import Draft202012Validator

    hints = typing.get_type_hints(settings)
    rules = {}
    for setting in dataclasses.fields(settings):
        where = f"benchmark {benchmark!r}: env setting {setting.name!r}"
        if setting.default is dataclasses.MISSING:
            raise UserError(f"{where} has no default: a cell whose config does not set it takes the declared default")
        rules[setting.name] = {**_json_type(hints[setting.name], where), **setting.metadata.get("schema", {})}
        if not Draft202012Validator(rules[setting.name]).is_valid(setting.default):
            raise UserError(f"{where}: its default {setting.default!r} does not satisfy its rules {rules[setting.name]}")
    return rules


def _json_type(hint: Any, where: str) -> dict[str, Any]:
    """The JSON-schema type (or enum) of annotation `hint`; UserError for one a YAML config cannot give."""
    if typing.get_origin(hint) is typing.Literal:
        return {"enum": list(typing.get_args(hint))}
    members = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
    if any(typing.get_origin(m) is typing.Literal for m in members):
        literal = [v for m in members if typing.get_origin(m) is typing.Literal for v in typing.get_args(m)]
        others = [m for m in members if typing.get_origin(m) is not typing.Literal]
        return {"anyOf": [{"enum": literal}, *(_json_type(m, where) for m in others)]}
    unknown = [m for m in members if m not in _JSON_TYPES]
    if unknown:
        raise UserError(f"{where}: type {hint} is not one a config can give (int, float, str, bool, None, a Literal, "
                        "or a union of them)")
    return {"type": [_JSON_TYPES[m] for m in members]}


# The observation key of the robot state, in every benchmark's observations (`envs.workers.serve` replies).
STATE = "state"
CAMERA_ROLES = ("main", "wrist")

_REGISTERED: dict[str, Benchmark] = {}


def register_benchmark(benchmark: Benchmark) -> Benchmark:
    """Register `benchmark` under its name (a benchmark's `benchmark.py` calls it); UserError when another
    declaration holds the name."""
    unknown = sorted(set(benchmark.cameras) - set(CAMERA_ROLES))
    if unknown or "main" not in benchmark.cameras:
        raise UserError(f"benchmark {benchmark.name!r}: cameras {sorted(benchmark.cameras)}: the roles are "
                        f"{', '.join(CAMERA_ROLES)}, and a main camera is required")
    if not (isinstance(benchmark.settings, type) and dataclasses.is_dataclass(benchmark.settings)):
        raise UserError(f"benchmark {benchmark.name!r}: settings {benchmark.settings!r} is not a dataclass (its env "
                        "settings, each field a keyword-only parameter of its vector env class)")
    settings_schema(benchmark.settings, benchmark.name)  # every setting a config can give, its default admitted
    for what, dim in (("action_dim", benchmark.action_dim), ("state_dim", benchmark.state_dim)):
        if not isinstance(dim, int) or isinstance(dim, bool) or dim < 1:
            raise UserError(f"benchmark {benchmark.name!r}: {what} {dim!r} is not a positive integer")
    expert = benchmark.scripted_expert
    if expert is not None and expert.suite not in benchmark.suites:
        raise UserError(f"benchmark {benchmark.name!r}: its scripted expert's suite {expert.suite!r} is not one of its "
                        f"suites ({', '.join(benchmark.suites)})")
    if expert is not None:  # its demonstrations name every component of the env's state and action
        for what, names, dim in (("state_names", expert.state_names, benchmark.state_dim),
                                 ("action_names", expert.action_names, benchmark.action_dim)):
            if len(names) != dim:
                raise UserError(f"benchmark {benchmark.name!r}: its scripted expert's {what} {list(names)} name "
                                f"{len(names)} components, but it declares {what.split('_')[0]}_dim {dim}")
    held = _REGISTERED.get(benchmark.name)
    if held is not None and held != benchmark:
        raise UserError(f"benchmark {benchmark.name!r} is declared twice ({held.suite_class}, {benchmark.suite_class})")
    _REGISTERED[benchmark.name] = benchmark
    return benchmark


# Declaration modules of benchmarks outside `envs/` (comma-separated module names), imported with the folders'.
PLUGINS_VARIABLE = "VQB_BENCHMARKS"


def _discover() -> None:
    """Import the `benchmark` module of every benchmark folder beside this file, then the modules that
    `VQB_BENCHMARKS` names (each registers itself); UserError naming a module that cannot be imported."""
    for folder in pkgutil.iter_modules([str(Path(__file__).parent)]):
        if folder.ispkg and (Path(__file__).parent / folder.name / "benchmark.py").is_file():
            importlib.import_module(f"{__package__}.{folder.name}.benchmark")
    for module in filter(None, (m.strip() for m in os.environ.get(PLUGINS_VARIABLE, "").split(","))):
        try:
            importlib.import_module(module)
        except ImportError as err:
            raise UserError(f"{PLUGINS_VARIABLE}: cannot import benchmark declaration module {module!r}: {err}") from None


class _Registered(Mapping):
    """{benchmark: {suite: SuiteSize}} of every registered benchmark, its folders found on first read. Found once,
    under a lock, and marked found only when every declaration is in: a thread reading it meanwhile (the workflow
    builds cells' configs in threads) waits rather than sees the benchmarks registered so far."""

    def __init__(self):
        self._found = False
        self._lock = threading.RLock()  # reentrant: a declaration module being imported may read the registry

    def _benchmarks(self) -> dict[str, Benchmark]:
        if not self._found:
            with self._lock:
                if not self._found:
                    _discover()
                    self._found = True
        return _REGISTERED

    def __getitem__(self, name: str) -> dict[str, SuiteSize]:
        return self._benchmarks()[name].suites

    def __iter__(self) -> Iterator[str]:
        return iter(sorted(self._benchmarks()))

    def __len__(self) -> int:
        return len(self._benchmarks())


BENCHMARK_SUITES: Mapping[str, dict[str, SuiteSize]] = _Registered()


def get_benchmark(name: str) -> Benchmark:
    """The benchmark `name`; UserError naming the registered ones when it is not."""
    lookup(BENCHMARK_SUITES, name, "benchmark")
    return _REGISTERED[name]


def cameras_of(keys: Iterable[str]) -> dict[str, str]:
    """Camera role -> observation key for an observation with `keys` when no benchmark is named (a policy
    driven by hand): the declaration of the registered benchmarks whose every camera key `keys` holds, the
    one declaring the most cameras; {} when none fits. UserError when the declarations that fit best
    disagree on a role's key (the observation does not say which benchmark it is from)."""
    keys = set(keys)
    fitting = [b.cameras for b in (get_benchmark(n) for n in BENCHMARK_SUITES) if set(b.cameras.values()) <= keys]
    if not fitting:
        return {}
    most = max(len(c) for c in fitting)
    best = {tuple(sorted(c.items())) for c in fitting if len(c) == most}
    if len(best) > 1:
        raise UserError(f"an observation with keys {sorted(keys)} fits the cameras of several benchmarks "
                        f"({sorted(str(dict(c)) for c in best)}): name its benchmark's cameras")
    return dict(next(iter(best)))


def benchmark_of(keys: Iterable[str]) -> str:
    """The registered benchmark an observation with `keys` comes from when none is named (a policy driven by
    hand): the one declaring the cameras `cameras_of` finds; UserError when no benchmark, or several, declare them."""
    keys = set(keys)
    cameras = cameras_of(keys)
    names = [name for name in BENCHMARK_SUITES if dict(get_benchmark(name).cameras) == cameras]
    if len(names) != 1:
        raise UserError(f"an observation with keys {sorted(keys)} fits the cameras of "
                        f"{' and '.join(names) or 'no registered benchmark'}: name its benchmark")
    return names[0]
