"""Simulated benchmarks, one folder each (`envs/<benchmark>/`), behind one protocol.

`BENCHMARK_SUITES` (`envs.registry`) names every registered benchmark, its suites and their sizes without
importing a simulator, so cell references, task ids and episode counts are checked while the workflow builds
the DAG (each benchmark's tests compare the sizes with the simulator's own lists). `make_suite` and `make_env` build a benchmark's suite and its batched worker env
(`envs.workers.WorkerVectorEnv`: reset a slot, submit a chunk, collect, release) from the benchmark's
name, importing only that benchmark's simulator; `benchmark_settings` builds a cell's env settings (the typed
dataclass its benchmark declares) from what its config gives, checked against that declaration, and
`env_settings` turns them into its env's arguments; `check_settings` refuses a setting that a config
gives for a benchmark that does not declare it, and `simulator_versions` reads (and checks) what a cell header records of the simulator.
The closed-loop runner, rollout calibration and replay recording take their suites, episode specs,
step limits (`SuiteTasks.max_steps`) and envs from here only.

A benchmark is a package `envs/<benchmark>/` whose `benchmark.py` registers its declaration
(`envs.registry.Benchmark`: its suites' sizes and where its suite class, a `SuiteTasks`, its vector env class,
a `WorkerVectorEnv`, and its `simulator_versions(pinned)` live); nothing here names one (docs/simulators.md:
adding a third one).
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

from vlaquantbench.envs.registry import BENCHMARK_SUITES, get_benchmark, settings_schema
from vlaquantbench.errors import UserError

if TYPE_CHECKING:
    from vlaquantbench.envs.episodes import SuiteTasks
    from vlaquantbench.envs.workers import WorkerVectorEnv


def check_ids(field: str, ids: Iterable[int], count: int, what: str) -> None:
    """UserError `<field>: <ids outside 0..count-1> ...` naming the field, the offending ids and the range.

    `what` says what the ids index, e.g. "<suite> has 10 tasks"."""
    outside = sorted({i for i in ids if not 0 <= i < count})
    if outside:
        shown = ", ".join(map(str, outside[:8])) + (", ..." if len(outside) > 8 else "")
        verb = "is" if len(outside) == 1 else "are"
        raise UserError(f"{field}: {shown} {verb} outside 0..{count - 1} ({what})")


def check_step_limit(field: str, max_steps: int, benchmark: str, suite: str, settle_steps: int = 0,
                     settle_field: str = "settle_steps") -> None:
    """UserError `<field>: <max_steps> ...` when an episode of `max_steps` policy steps (and `settle_steps` settle
    steps, where the benchmark's env settles) would outrun the simulator's horizon (`SuiteSize.horizon`)."""
    horizon = BENCHMARK_SUITES[benchmark][suite].horizon
    settled = settle_steps if horizon.counts_settle_steps else 0
    if max_steps + settled > horizon.steps:
        after = f" after {settle_field} {settled}" if settled else ""
        raise UserError(f"{field}: {max_steps} steps{after} is beyond {suite}'s limit of {horizon.steps} env steps an "
                        f"episode ({horizon.source}); set it to at most {horizon.steps - settled}")


def make_suite(benchmark: str, suite: str) -> SuiteTasks:
    """Suite `suite` of `benchmark`; UserError naming the benchmark or suite if either is unknown."""
    return get_benchmark(benchmark).resolve("suite_class")(suite)


def make_env(benchmark: str, suite: str | SuiteTasks, num_envs: int, **settings: Any) -> WorkerVectorEnv:
    """`num_envs` worker slots of `benchmark` on `suite` (a name or a built suite). `settings` are the
    benchmark's env settings (the keyword-only parameters of its vector env class; camera_size None renders
    no image where the env allows it); UserError naming an unknown one, before any suite or worker."""
    env_class = get_benchmark(benchmark).resolve("env_class")
    accepted = _settings(env_class)
    unknown = sorted(set(settings) - set(accepted))
    if unknown:
        raise UserError(f"unknown {benchmark} env setting(s) {', '.join(unknown)}; known: {', '.join(accepted)}")
    if isinstance(suite, str):
        suite = make_suite(benchmark, suite)
    return env_class(suite, num_envs, **settings)


def _settings(env_class: type) -> list[str]:
    """The env settings a vector env class takes: its keyword-only parameters."""
    return [name for name, parameter in inspect.signature(env_class).parameters.items()
            if parameter.kind is inspect.Parameter.KEYWORD_ONLY]


def benchmark_settings(benchmark: str, given: Mapping[str, Any], fields: Mapping[str, str],
                       conventions: Mapping[str, Any] | None = None) -> Any:
    """The env settings of a cell (or a recording) of `benchmark`: its declared settings dataclass
    (`envs.registry.Benchmark.settings`) with the values `given` (setting -> value, each set by the config field
    `fields[setting]`), then `conventions` (a model's released client's, e.g. its controller mode and MuJoCo pin)
    for the declared settings not given, the declared default elsewhere; conventions for settings it does not
    declare are none of its cells'. UserError naming the field and the benchmark, before any simulator starts, for
    a setting it does not declare (`check_settings`) or a value its declaration does not admit (`settings_schema`)."""
    from jsonschema import Draft202012Validator

    check_settings(benchmark, {name: fields[name] for name in given})
    declared = get_benchmark(benchmark)
    rules = settings_schema(declared.settings, benchmark)
    for name, value in given.items():
        problems = [error.message for error in Draft202012Validator(rules[name]).iter_errors(value)]
        if problems:
            raise UserError(f"{fields[name]}: {'; '.join(problems)} ({benchmark}'s env setting {name}: {rules[name]})")
    taken = {name: value for name, value in (conventions or {}).items() if name in declared.setting_names}
    return declared.settings(**{**taken, **given})


def env_settings(settings: Any, reads_images: bool = True) -> dict[str, Any]:
    """The keyword arguments of a cell's vector env (`make_env`): its typed env settings (`benchmark_settings`),
    except that a policy that reads no image (`reads_images`) gets none rendered (camera_size None)."""
    values = {f.name: getattr(settings, f.name) for f in dataclasses.fields(settings)}
    if not reads_images and "camera_size" in values:
        values["camera_size"] = None
    return values


def check_settings(benchmark: str, given: Mapping[str, str]) -> None:
    """Refuse env settings a config sets for a cell of `benchmark` that it does not declare. `given`: each env
    setting the config names (a runner option that is no policy option, `config.study.RunnerConfig`) -> the config
    field that names it (e.g. `study.runner.settle_steps`). One `benchmark` does not declare would be silently
    unused by its env: UserError `<field>: ...` naming the setting, the benchmark, the settings it takes and the
    benchmarks that take it, if any."""
    declared = get_benchmark(benchmark).setting_names
    refused = [name for name in given if name not in declared]
    if refused:
        takers = {name: [other for other in BENCHMARK_SUITES if name in get_benchmark(other).setting_names]
                  for name in refused}

        def whose(name: str) -> str:
            return f"{name} is {'/'.join(takers[name])}'s" if takers[name] else f"no registered benchmark takes {name}"

        elsewhere = sorted({t for ts in takers.values() for t in ts})
        raise UserError("; ".join(
            f"{given[name]}: {name!r} is not an env setting of {benchmark} (it takes {', '.join(declared) or 'none'}; "
            f"{whose(name)})" for name in refused)
            + "; remove it" + (f", or set it under study.models.<model>.runner for the models whose cells run on "
                               f"{'/'.join(elsewhere)} only"
                               if elsewhere and any(given[name].startswith("study.runner.") for name in refused) else ""))


def simulator_versions(benchmark: str, pinned: str | None = None) -> dict[str, Any]:
    """The simulator versions a cell header records; UserError when MuJoCo is not `pinned` (a cell's
    `runner.mujoco`; None: the active software environment's pin)."""
    return get_benchmark(benchmark).resolve("simulator_versions")(pinned=pinned)
