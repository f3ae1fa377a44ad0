"""Simulated benchmarks, one folder each (`envs/libero/`, `envs/metaworld/`), behind one protocol.

`BENCHMARK_SUITES` names every benchmark and its suites without importing a simulator, so cell
references are checked while the workflow builds the DAG. `make_suite` and `make_env` build a
benchmark's suite and its batched worker env (`envs.workers.WorkerVectorEnv`: reset a slot, submit
a chunk, collect, release) from the benchmark's name, importing only that benchmark's simulator.
"""

from __future__ import annotations

import importlib
import inspect
from typing import TYPE_CHECKING, Any

from vlaquantbench.errors import UserError, lookup

if TYPE_CHECKING:
    from vlaquantbench.envs.episodes import SuiteTasks
    from vlaquantbench.envs.workers import WorkerVectorEnv

BENCHMARK_SUITES = {
    "libero": ("libero_spatial", "libero_object", "libero_goal", "libero_10"),
    "metaworld": ("metaworld_easy", "metaworld_medium", "metaworld_hard", "metaworld_very_hard",
                  "metaworld_mt10", "metaworld_mt50"),
}
# Each benchmark's package exports its suite and vector env classes under these names.
_CLASSES = {"libero": ("LiberoSuite", "LiberoVectorEnv"), "metaworld": ("MetaWorldSuite", "MetaWorldVectorEnv")}


def _benchmark_class(benchmark: str, which: int) -> type:
    names = lookup(_CLASSES, benchmark, "benchmark")
    return getattr(importlib.import_module(f"vlaquantbench.envs.{benchmark}"), names[which])


def make_suite(benchmark: str, suite: str) -> SuiteTasks:
    """Suite `suite` of `benchmark`; UserError naming the benchmark or suite if either is unknown."""
    return _benchmark_class(benchmark, 0)(suite)


def make_env(benchmark: str, suite: str | SuiteTasks, num_envs: int, **settings: Any) -> WorkerVectorEnv:
    """`num_envs` worker slots of `benchmark` on `suite` (a name or a built suite). `settings` are the
    benchmark's env settings (LIBERO: camera_size, settle_steps, control_mode, mujoco; Meta-World:
    camera_size, None to render no image); UserError naming an unknown one, before any suite or worker."""
    env_class = _benchmark_class(benchmark, 1)
    accepted = [name for name, parameter in inspect.signature(env_class).parameters.items()
                if parameter.kind is inspect.Parameter.KEYWORD_ONLY]
    unknown = sorted(set(settings) - set(accepted))
    if unknown:
        raise UserError(f"unknown {benchmark} env setting(s) {', '.join(unknown)}; known: {', '.join(accepted)}")
    if isinstance(suite, str):
        suite = make_suite(benchmark, suite)
    return env_class(suite, num_envs, **settings)
