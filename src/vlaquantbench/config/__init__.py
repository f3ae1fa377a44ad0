"""Every YAML file the project reads goes through `load_yaml(path, schema)`: parsed, then validated by
jsonschema (Draft 2020-12, the validator Snakemake's `validate` uses) against
`vlaquantbench/config/schemas/<schema>.schema.yaml`.

    table = load_yaml("config/tables/lattice.yaml", "table")

A file that does not satisfy its schema raises one `UserError` naming the file and, for each
violation, the field path and what is allowed (the allowed keys of a misspelt one, the allowed
values of an enum). Nothing here imports torch: the workflow parses configs without it.
"""

from __future__ import annotations

import functools
from importlib import resources
from pathlib import Path
from typing import Any

from typing import TYPE_CHECKING

import yaml

from vlaquantbench.errors import UserError
from vlaquantbench.textfiles import read_parsed

if TYPE_CHECKING:
    from jsonschema.exceptions import ValidationError

# libyaml's parser where PyYAML was built with it: the workflow parses every table definition while it
# builds the DAG, and the pure-Python parser made that several seconds.
YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

SCHEMAS = ("config", "table", "layer_index_table", "figure", "scopes", "cohort", "replay_study", "checkpoint_stamp")
# The Snakefile's `configfile:`; `snakemake --configfile FILE` merges FILE over it.
WORKFLOW_CONFIG = Path("config/config.yaml")


def schema_path(name: str) -> Path:
    """The schema file `<name>.schema.yaml` (package data; `workflow/schemas/` links to it)."""
    if name not in SCHEMAS:
        raise ValueError(f"no schema {name!r}; schemas: {', '.join(SCHEMAS)}")
    return Path(str(resources.files(__package__).joinpath(f"schemas/{name}.schema.yaml")))


@functools.cache
def schema(name: str) -> dict[str, Any]:
    from jsonschema import Draft202012Validator  # here, not at import: a workflow job that only renders skips it

    loaded = yaml.load(schema_path(name).read_text(), Loader=YAML_LOADER)
    Draft202012Validator.check_schema(loaded)
    return loaded


@functools.cache
def _validator(name: str, subschema: tuple[str, ...]):
    from jsonschema import Draft202012Validator

    rules = schema(name)
    for key in subschema:
        rules = rules["properties"][key]
    return Draft202012Validator(rules)


def validate(data: Any, schema_name: str, where: str, subschema: tuple[str, ...] = ()) -> Any:
    """`data` if it satisfies schema `schema_name` (or the part of it at the property path `subschema`,
    e.g. ("study",)); else UserError `<where>: <field.path>: <problem>` for every violation."""
    errors = sorted(_validator(schema_name, tuple(subschema)).iter_errors(data), key=lambda e: [str(p) for p in e.absolute_path])
    if errors:
        lines = [_describe(error, subschema) for error in errors]
        raise UserError(f"{where}: " + ("\n  ".join([""] + lines) if len(lines) > 1 else lines[0]))
    return data


def field_schema(schema_name: str, *path: str) -> dict[str, Any]:
    """The rules of one field of schema `schema_name`, e.g. ("study", "execution", "num_envs")."""
    rules = schema(schema_name)
    for key in path:
        rules = rules["properties"][key]
    return rules


def integer_option(rules: dict[str, Any]):
    """An argparse `type` for an integer option: the text parsed and checked against the JSON-schema `rules`
    (a config field's, from `field_schema`, when the option sets that field), so that an out-of-range value
    is refused by argparse naming the option, e.g. `argument --num-envs: 0 is less than the minimum of 1`."""

    def parse(text: str) -> int:
        import argparse

        from jsonschema import Draft202012Validator

        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        problems = [error.message for error in Draft202012Validator(rules).iter_errors(value)]
        if problems:
            raise argparse.ArgumentTypeError("; ".join(problems))
        return value

    return parse


def load_yaml(path: str | Path, schema_name: str) -> Any:
    """Parse the YAML file `path` and validate it against schema `schema_name`."""
    return validate(_parse(path), schema_name, str(path))


def _parse(path: str | Path) -> Any:
    data = read_parsed(path, lambda text: yaml.load(text, Loader=YAML_LOADER), "YAML", (yaml.YAMLError,))
    return {} if data is None else data


def load_workflow_config(path: str | Path, base: str | Path = WORKFLOW_CONFIG) -> dict[str, Any]:
    """The config `snakemake --configfile path` runs with, validated as the Snakefile validates it:
    `base` (the Snakefile's own config file, when it exists) with `path` merged over it key by key
    (nested mappings merged, every other value replaced, as Snakemake's `update_config` does)."""
    path, base = Path(path), Path(base)
    if not base.is_file() or base.resolve() == path.resolve():
        return load_yaml(path, "config")
    merged = _merge(_parse(base), _parse(path))
    return validate(merged, "config", workflow_config_name(path, base))


def workflow_config_name(path: str | Path, base: str | Path = WORKFLOW_CONFIG) -> str:
    """How errors name the config `load_workflow_config(path, base)` gives: the file, and the base it was merged over."""
    path, base = Path(path), Path(base)
    return str(path) if not base.is_file() or base.resolve() == path.resolve() else f"{path} (merged over {base})"


def _merge(config: dict[str, Any], overwrite: dict[str, Any]) -> dict[str, Any]:
    merged = dict(config)
    for key, value in overwrite.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = _merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def _describe(error: ValidationError, prefix: tuple[str, ...]) -> str:
    path = ".".join(str(p) for p in (*prefix, *error.absolute_path)) or "(top level)"
    if error.validator == "additionalProperties" and isinstance(error.instance, dict):
        allowed = sorted(error.schema.get("properties", {}))
        unknown = sorted(set(error.instance) - set(allowed))
        keys = ", ".join(repr(k) for k in unknown)
        return f"{path}: unknown key {keys}; allowed keys: {', '.join(allowed)}"
    if error.validator == "enum":
        return f"{path}: {error.instance!r} is not allowed; allowed values: {', '.join(map(str, error.validator_value))}"
    return f"{path}: {error.message}"
