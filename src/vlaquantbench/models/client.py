"""Each model's released client conventions, and the cell values that deviate from them.

The paper evaluates every checkpoint under its own released inference client (Sec. 5): how many of
the predicted actions are executed before observing again, how many episodes a task gets, whether
the arm controller takes delta or absolute end-effector poses, the MuJoCo version the client's
environment pins, and the fixed model seed of a deterministic head.

A model's `client.py` declares `CLIENT`, and may declare `BENCHMARK_CLIENTS` (`{benchmark: ClientConventions}`:
its client's conventions on a benchmark where they differ from `CLIENT`), so conventions are keyed by (model,
benchmark) and live in the model's folder; `cells.cell_config` fills a cell's runner from its benchmark's and
records every value the study sets differently under `overrides` in the cell config (and so in the
header). Adapters and the runner then check that what runs is what the cell says. Beside `CLIENT`, a
model's `client.py` may declare `ADAPTER_CONVENTIONS` (`{benchmark: conventions}`, a frozen dataclass of its
own: how its client feeds the policy that benchmark's observations and reads its actions, e.g. X-VLA's domain
id; like the adapter's code, not hashed with the cell), `STEP_LIMITS` (`{benchmark: {suite: policy steps}}`, its
client's step limits; a benchmark with a limit of its own, Meta-World's 500, needs none) and `ENVIRONMENT` (the
software environment its cells run in, `vlaquantbench.software_env`; main when absent). They are the
model's own facts: no module outside `models/` names a model.
"""

from __future__ import annotations

import dataclasses
import importlib
from dataclasses import dataclass

from vlaquantbench.config import validate
from vlaquantbench.errors import UserError


@dataclass(frozen=True)
class ClientConventions:
    """A released client's conventions. The runner options they set and the episodes per task satisfy the
    rules of `study.runner` and `study.episodes_per_task` in the config schema (the YAML values they stand
    in for), and the env settings they set (controller mode, MuJoCo pin) the declaration of every registered
    benchmark that takes them (`envs.benchmark_settings`), checked when the conventions are built, in a model's
    client.py or read back from a cell config."""

    executed_chunk: int  # actions executed per predicted chunk
    episodes_per_task: int
    control_mode: str  # arm controller: "delta" or "absolute" end-effector poses
    mujoco: str  # the MuJoCo version the client's environment pins
    model_seed: int | None = None  # fixed model seed of a deterministic head (None: per-episode streams)
    source: str = ""  # where the values come from

    def __post_init__(self):
        where = f"client conventions ({self.source or 'no source'})"
        validate(self.runner(), "config", where, subschema=("study", "runner"))
        from vlaquantbench.envs import BENCHMARK_SUITES, benchmark_settings
        from vlaquantbench.envs.registry import get_benchmark

        for benchmark in BENCHMARK_SUITES:
            taken = {k: v for k, v in self.runner().items() if k in get_benchmark(benchmark).setting_names}
            benchmark_settings(benchmark, taken, {k: f"{where}: study.runner.{k}" for k in taken})
        validate(self.episodes_per_task, "config", f"{where}: episodes_per_task", subschema=("study", "episodes_per_task"))
        if self.model_seed is not None and (not isinstance(self.model_seed, int) or isinstance(self.model_seed, bool)):
            raise UserError(f"{where}: model_seed: {self.model_seed!r} is not an integer or None")

    def runner(self) -> dict:
        """The runner options these conventions set (hashed with the cell)."""
        return {"executed_chunk": self.executed_chunk, "control_mode": self.control_mode, "mujoco": self.mujoco}

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def _client(model: str):
    from vlaquantbench.models.registry import model_package

    return importlib.import_module(f"{model_package(model)}.client")


def client_conventions(model: str, benchmark: str | None = None) -> ClientConventions:
    """The model's client conventions on `benchmark`: its `client.py`'s `BENCHMARK_CLIENTS[benchmark]` where it
    declares one, else its `CLIENT` (also for `benchmark` None); UserError for an unknown model, or for a
    `BENCHMARK_CLIENTS` key that names no registered benchmark."""
    per_benchmark = _per_benchmark(model, "BENCHMARK_CLIENTS") or {}
    return per_benchmark.get(benchmark, _client(model).CLIENT)


def _per_benchmark(model: str, name: str) -> dict | None:
    """The model's client.py mapping `name` ({benchmark: ...}); None where it declares none; UserError naming a key
    that is no registered benchmark."""
    per_benchmark = getattr(_client(model), name, None)
    if per_benchmark:
        from vlaquantbench.envs import BENCHMARK_SUITES

        unknown = sorted(set(per_benchmark) - set(BENCHMARK_SUITES))
        if unknown:
            raise UserError(f"model {model!r}: {name} of its client.py names {', '.join(unknown)}; "
                            f"registered benchmarks: {', '.join(BENCHMARK_SUITES)}")
    return per_benchmark


def adapter_conventions(model: str, benchmark: str):
    """The model's adapter conventions on `benchmark`: `ADAPTER_CONVENTIONS[benchmark]` of its client.py; None for a
    model whose client.py declares none (its adapter feeds every benchmark alike). UserError naming the model and
    the benchmark when it declares them for other benchmarks only (its client never ran there), or naming a key
    that is no registered benchmark."""
    per_benchmark = _per_benchmark(model, "ADAPTER_CONVENTIONS")
    if per_benchmark is None:
        return None
    if benchmark not in per_benchmark:
        raise UserError(f"model {model!r} has no adapter conventions on benchmark {benchmark!r}: its client.py "
                        f"ADAPTER_CONVENTIONS declares {', '.join(per_benchmark) or 'none'} (how its client feeds the "
                        f"policy there is unknown)")
    return per_benchmark[benchmark]


def step_limit(model: str, benchmark: str, suite: str) -> int:
    """Policy steps before an unfinished episode of `model` on `suite` counts as a failure: the model's
    client's (`STEP_LIMITS`), else the benchmark's own (`envs.registry.SuiteSize.step_limit`); UserError naming the
    model, benchmark and suite when neither has one (the model's client never ran there)."""
    from vlaquantbench.envs import BENCHMARK_SUITES

    limits = getattr(_client(model), "STEP_LIMITS", {}).get(benchmark, {})
    own = BENCHMARK_SUITES[benchmark][suite].step_limit
    if suite not in limits and own is None:
        declared = ", ".join(f"{b}/{s}" for b, suites in getattr(_client(model), "STEP_LIMITS", {}).items() for s in suites)
        raise UserError(f"model {model!r} has no step limit on {benchmark} suite {suite!r} (its client.py STEP_LIMITS "
                        f"declares {declared or 'none'}, and {benchmark} has no limit of its own)")
    return limits.get(suite, own)


def environment_name(model: str) -> str:
    """The software environment the model's cells run in (`ENVIRONMENT` of its client.py; main otherwise)."""
    from vlaquantbench.software_env import MAIN

    return getattr(_client(model), "ENVIRONMENT", MAIN)
