"""What a cell's records must hold: JSON Schemas for its run header and for each episode, with the
episode's bounds taken from the header (suite, tasks, episode indices, step limit) and the protocol's
seeds and init states.

    check = EpisodeCheck(header, source)   # refuses a header without suite, model, seed, ...
    check(row, f"{path}:{line}")           # refuses one episode, naming where it is

The same check reads the authors' `.jsonl` lines, a cell folder's `episodes.parquet` rows and
the runner's journal lines, so a string `"false"` is refused as a success everywhere instead of being
cast to True, and a task id outside the header's suite is refused on its own line.

The schemas (`schemas/*.schema.yaml`, JSON Schema draft-07) are compiled by fastjsonschema: it
checks the 12,980 reference episodes in about 0.15 s where jsonschema's validator takes 1.3-2 s, and
every table job reads its cells through here.
"""

from __future__ import annotations

import copy
import functools
import json
from importlib import resources
from pathlib import Path
from typing import Any, Callable

import fastjsonschema
import pandas as pd
import yaml

from vlaquantbench.envs import BENCHMARK_SUITES
from vlaquantbench.envs.episodes import SEED_STRIDE
from vlaquantbench.models.client import step_limit as model_step_limit
from vlaquantbench.errors import UserError


@functools.cache
def _parsed(name: str) -> dict[str, Any]:
    return yaml.safe_load(resources.files(__package__).joinpath(f"schemas/{name}.schema.yaml").read_text())


def _load(name: str) -> dict[str, Any]:
    """A copy of schema `name` (schemas/<name>.schema.yaml), to bound by a header."""
    return copy.deepcopy(_parsed(name))


@functools.cache
def _compiled(schema_json: str) -> Callable[[Any], Any]:
    return fastjsonschema.compile(json.loads(schema_json))


def _validator(schema: dict[str, Any]) -> Callable[[Any], Any]:
    """The compiled schema, once per process for each distinct schema (a table job's cells share a few)."""
    return _compiled(json.dumps(schema, sort_keys=True))


def _violation(err) -> str:
    """`field: value problem (why the bound is what it is)` from a fastjsonschema error."""
    field = ".".join(str(part) for part in err.path[1:])
    if err.rule == "required":
        missing = ", ".join(name for name in err.rule_definition if name not in err.value)
        return f"{field + ': ' if field else ''}lacks required field(s) {missing}"
    problem = err.message.split(" ", 1)[1] if err.message.startswith(err.name + " ") else err.message
    described = err.definition.get("description") if isinstance(err.definition, dict) else None
    return f"{field or '(top level)'}: {err.value!r} {problem}" + (f" ({described})" if described else "")


def _checked(validate: Callable[[Any], Any], record: dict[str, Any], where: str) -> None:
    try:
        validate(record)
    except fastjsonschema.JsonSchemaValueException as err:
        raise UserError(f"{where}: {_violation(err)}") from None


def header_schema() -> dict[str, Any]:
    """The header schema with each benchmark's suites as the allowed values."""
    schema = _load("record_header")
    schema["properties"]["benchmark"]["enum"] = sorted(BENCHMARK_SUITES)
    schema["allOf"] = [
        {"if": {"properties": {"benchmark": {"const": name}}},
         "then": {"properties": {"suite": {"enum": list(suites), "description": f"the suites of {name}"}}}}
        for name, suites in BENCHMARK_SUITES.items()
    ]  # fmt: skip
    return schema


def declared_tasks(header: dict[str, Any]) -> list[int] | None:
    """The task ids a header lists (this project's cells, under `config.tasks`); None when it lists none."""
    return header.get("tasks") or (header.get("config") or {}).get("tasks")


def step_limit(header: dict[str, Any], source: Path) -> int:
    """The cell's step limit: the header's `max_steps`, else its model's limit on its suite (the authors' records)."""
    if header.get("max_steps"):
        return int(header["max_steps"])
    try:
        return model_step_limit(header["model"], header["benchmark"], header["suite"])
    except UserError as err:
        raise UserError(f"{source}: the header records no max_steps and {err}") from None


class EpisodeCheck:
    """The episode schema of one cell, bounded by its run header (checked first)."""

    def __init__(self, header: dict[str, Any], source: str | Path):
        _checked(_validator(header_schema()), header, f"{source}: run header")
        self.header = header
        suite, tasks, per_task = header["suite"], declared_tasks(header), header["episodes_per_task"]
        schema = _load("episode")
        properties = schema["properties"]
        properties["suite"] = {"const": suite, "description": "the header's suite"}
        properties["model"] = {"const": header["model"], "description": "the header's model"}
        if tasks:
            properties["task_id"] = {"enum": sorted(tasks), "description": "the tasks the header lists"}
        else:
            count = BENCHMARK_SUITES[header["benchmark"]][suite].tasks
            properties["task_id"] |= {"maximum": count - 1, "description": f"{suite} has {count} tasks: 0..{count - 1}"}
        properties["episode"] |= {"maximum": per_task - 1, "description": f"the header declares {per_task} episodes per task"}
        limit = step_limit(header, Path(source))
        properties["steps"] |= {"maximum": limit, "description": f"the step limit of {header['model']} on {suite}"}
        self.validate = _validator(schema)

    def __call__(self, episode: dict[str, Any], where: str) -> None:
        """Refuse `episode` (a dict of its present, non-null fields) with UserError `<where>: <field>: <problem>`."""
        _checked(self.validate, episode, where)
        # The protocol relates fields of one episode, which JSON Schema cannot express (draft-07 has no
        # $data): LIBERO episode i of a task starts from official init state i, with seed
        # SEED_STRIDE * task + episode + the run seed.
        task, index = episode["task_id"], episode["episode"]
        seed = SEED_STRIDE * task + index + self.header["seed"]
        if episode["seed"] != seed:
            raise UserError(f"{where}: seed: {episode['seed']} is not the protocol's {SEED_STRIDE} * task_id + episode "
                            f"+ run seed = {seed} (task {task}, episode {index}, run seed {self.header['seed']})")
        if "init_state_id" in episode and episode["init_state_id"] != index:
            raise UserError(f"{where}: init_state_id: {episode['init_state_id']} is not the episode index {index} "
                            "(episode i of a task starts from init state i)")
        if "task_name" in episode or "task_variation" in episode:
            self._check_task(episode, where)

    def _check_task(self, episode: dict[str, Any], where: str) -> None:
        """The task an episode names is its task id's in the header's suite (a table selects a task's episodes by
        name), and the placement it records is the one its task, seed and index start it from (Meta-World)."""
        suite = _suite(self.header["benchmark"], self.header["suite"])
        task = episode["task_id"]
        if "task_name" in episode and episode["task_name"] != suite.task(task).name:
            raise UserError(f"{where}: task_name: {episode['task_name']!r} is not task {task} of {suite.name}, "
                            f"{suite.task(task).name!r}")
        if "task_variation" not in episode:
            return
        if not hasattr(suite, "task_variation"):
            raise UserError(f"{where}: task_variation: {self.header['benchmark']} episodes start from no seeded "
                            "task variation")
        spec = suite.episode_spec(task, episode["episode"], self.header["seed"])
        drawn = suite.task_variation(spec)
        if tuple(episode["task_variation"]) != drawn:
            shown = lambda values: "[" + ", ".join(f"{float(x):.4f}" for x in values) + "]"  # noqa: E731
            raise UserError(f"{where}: task_variation: {shown(episode['task_variation'])} is not the placement "
                            f"{shown(drawn)} that episode {spec.episode} of {suite.task(task).name} starts from "
                            f"(task variation {spec.init_state_id}, drawn from seed "
                            f"{suite.variation_seed(task, spec.init_state_id)})")


@functools.cache
def _suite(benchmark: str, name: str):
    """The suite a header names, built once per process (its task names; Meta-World's placements)."""
    from vlaquantbench.envs import make_suite

    return make_suite(benchmark, name)


def present(row: dict[str, Any]) -> dict[str, Any]:
    """The fields of `row` that hold a value (parquet nulls and pandas' NA/NaT dropped)."""
    return {key: value for key, value in row.items() if value is not None and value is not pd.NA}
