"""Cell references in the authors' naming -> canonical cell configs and their hashes.

A cell reference is `<benchmark>/<suite>/<model>/<cell>`; the cell name follows the grammar

    [seed<N>-][steps<N>-]<method>-<preset>-<scope>[-<subset>]

    method  rtn | ablate | calib[_<comps>][_a<alpha*100>] | calib_set<k>_<comps>[_a<alpha*100>]
            | awq | nf4 | int8 | smoothquant
    comps   ah | llm | ve | all   (all = every component of the scope)
    scope   ve | mp | llm | ah | e2e | ve_mp_llm
    subset  a named subset of `config/scopes.yaml` for this model (its only/exclude patterns)

`seed<N>` offsets every episode seed by N; `steps<N>` sets the number of flow-matching
integration steps. `calib_set<k>` collects calibration statistics on init states
`first + 2k, first + 2k + 1` (the paper's disjoint calibration sets). `awq` cells collect their
statistics in the same calibration episodes: mean |x| and `AWQ_SAMPLE_ROWS` sampled input rows of
every layer of the scope, without rollout smoothing or clipping. `smoothquant` cells always smooth
(SmoothQuant's per-channel migration is the method): alpha = `SMOOTHQUANT_ALPHA`, the paper's LLM
deployment setting, from the input absmax of the same rollout calibration episodes, no clipping (the
paper's 512 text calibration samples cannot be drawn offline; the header's format says which). The canonical cell config
(`cell_config`) holds everything that changes an episode's outcome; `config_hash` names the cell's
output folder, so two cells share a folder exactly when they would produce the same records.
"""

from __future__ import annotations

import hashlib
import json
import re
from typing import Any

from vlaquantbench.errors import UserError

SCOPES = ("ve", "mp", "llm", "ah", "e2e", "ve_mp_llm")
SCOPE_COMPONENTS = {
    "ve": ["ve"],
    "mp": ["mp"],
    "llm": ["llm"],
    "ah": ["ah"],
    "e2e": ["ve", "mp", "llm", "ah"],
    "ve_mp_llm": ["ve", "mp", "llm"],
}
PLAIN_METHODS = ("rtn", "ablate", "awq", "nf4", "int8", "smoothquant")
# Cell methods that are RTN grids in the quantizer: ablate = RTN on a named subset, calib* = RTN after
# rollout smoothing/clipping; every other method names a registered quantization method.
RTN_METHODS = ("rtn", "ablate")
CALIBRATION_COMPONENTS = ("ah", "llm", "ve", "all")


def quantizer_method(cell_method: str) -> str:
    """The quantization method (`vlaquantbench.quant` dispatch name) a cell's method runs."""
    return "rtn" if cell_method in RTN_METHODS or cell_method.startswith("calib") else cell_method

_CELL_NAME = re.compile(
    r"^(?:seed(?P<seed>\d+)-)?(?:steps(?P<steps>\d+)-)?"
    r"(?P<method>[a-z0-9_]+)-(?P<preset>[A-Z][A-Z0-9]*)-(?P<scope>ve_mp_llm|e2e|ve|mp|llm|ah)"
    r"(?:-(?P<subset>[a-z0-9_]+))?$"
)
_CALIB_METHOD = re.compile(
    r"^calib(?:_set(?P<set>\d+))?(?:_(?P<comps>ah|llm|ve|all))?(?:_a(?P<alpha>\d+))?$"
)

# Runner options that change what an episode does (and therefore the records); execution
# details that do not (number of parallel environments, progress display) stay out of the hash.
DEFAULT_RUNNER = {
    "device": "cpu",
    "dtype": "float32",
    "executed_chunk": 10,
    "flow_steps": 10,
    "max_steps": None,  # None: the suite's step limit for the model family
    "camera_size": 256,
    "settle_steps": 10,
    # auto | captured | eager (`models.adapter.resolve_sampler`); hashed because the captured and
    # eager samplers order floating-point operations differently, so actions can differ in the last bits.
    "sampler": "auto",
}
RUNNER_OPTIONS = tuple(DEFAULT_RUNNER)
AWQ_SAMPLE_ROWS = 128  # input rows per layer for AWQ's scale search (the paper: 128 calibration samples)
SMOOTHQUANT_ALPHA = 0.85  # the paper's SmoothQuant deployment migration strength (app. real-kernel settings)
DEFAULT_CALIBRATION = {
    "episodes": 2,
    "first_init_state": 20,
    "tasks": 1,
    "alpha": 0.5,
    "quantile": 0.999,
}


def parse_cell_name(name: str) -> dict[str, Any]:
    """Split a cell name into its fields; UserError naming the cell and the grammar on a mismatch."""
    match = _CELL_NAME.match(name)
    if not match:
        raise UserError(
            f"cell name {name!r} does not follow "
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
                f"cell {name!r}: method {method!r} is not calib[_set<k>][_<{'|'.join(CALIBRATION_COMPONENTS)}>][_a<alpha*100>]"
            )
        calibration = {
            "set": int(calib["set"]) if calib["set"] is not None else None,
            "components": calib["comps"] or "all",
            "alpha": int(calib["alpha"]) / 100 if calib["alpha"] is not None else None,
        }
    elif method not in PLAIN_METHODS:
        raise UserError(
            f"cell {name!r}: unknown method {method!r}; expected one of "
            f"{', '.join(PLAIN_METHODS)} or calib[_set<k>]_<comps>[_a<alpha*100>]"
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


def _subset_patterns(ref: str, model: str, scope: str, subset: str | None) -> tuple[list[str] | None, list[str] | None]:
    if subset is None:
        return None, None
    from vlaquantbench.quant.subsets import get_subset

    try:
        named = get_subset(model, subset)
    except UserError as err:
        raise UserError(f"cell {ref!r}: {err}") from None
    if named.scope != scope:
        raise UserError(f"cell {ref!r}: subset {subset!r} of {model} is defined on scope {named.scope!r}, not {scope!r}")
    return (list(named.only) if named.only else None, list(named.exclude) if named.exclude else None)


def _check_preset(ref: str, preset: str) -> None:
    from vlaquantbench.quant.presets import parse_preset

    try:
        parse_preset(preset)
    except UserError as err:
        raise UserError(f"cell {ref!r}: {err}") from None


def cell_config(ref: str, study: dict[str, Any]) -> dict[str, Any]:
    """The canonical config of the cell `ref` under `study` (the config's `study` section).

    Raises UserError naming the reference and the missing/bad field before any work starts.
    """
    benchmark, suite, model, name = parse_ref(ref)
    fields = parse_cell_name(name)
    models = study.get("models", {})
    if model not in models:
        raise UserError(f"cell {ref!r}: model {model!r} is not in study.models ({', '.join(models) or 'none'})")
    model_cfg = models[model]
    runner = {**DEFAULT_RUNNER, **{k: v for k, v in study.get("runner", {}).items() if k in RUNNER_OPTIONS}}
    if fields["flow_steps"] is not None:
        runner["flow_steps"] = fields["flow_steps"]
    _check_preset(ref, fields["preset"])
    only, exclude = _subset_patterns(ref, model, fields["scope"], fields["subset"])
    seed = int(study.get("seed", 0)) + fields["seed_offset"]
    cfg: dict[str, Any] = {
        "ref": ref,
        "cell": name,
        "benchmark": benchmark,
        "suite": suite,
        "model": model,
        "variant": model_cfg.get("variant", "full"),
        "checkpoint": model_cfg.get("checkpoint"),
        "revision": model_cfg.get("revision"),
        "method": fields["method"],
        "preset": fields["preset"],
        "scope": fields["scope"],
        "subset": fields["subset"],
        "only": only,
        "exclude": exclude,
        "calibration": _calibration(ref, fields, study, seed),
        "seed": seed,
        "tasks": _tasks(ref, study),
        "episodes_per_task": int(study.get("episodes_per_task", 20)),
        "runner": runner,
    }
    return canonical(cfg)


def _tasks(ref: str, study: dict[str, Any]) -> list[int]:
    tasks = study.get("tasks", 10)
    if isinstance(tasks, int):
        return list(range(tasks))
    if not tasks or not all(isinstance(t, int) and t >= 0 for t in tasks):
        raise UserError(f"cell {ref!r}: study.tasks must be a count or a list of task ids, got {tasks!r}")
    return sorted(set(tasks))


def _calibration(ref: str, fields: dict[str, Any], study: dict[str, Any], seed: int) -> dict[str, Any] | None:
    parsed = fields["calibration"]
    if parsed is None and fields["method"] not in ("awq", "smoothquant"):
        return None
    settings = {**DEFAULT_CALIBRATION, **study.get("calibration", {})}
    observed = _observed(ref, fields, settings)
    first = int(settings["first_init_state"]) + 2 * ((parsed or {}).get("set") or 0)
    episodes = int(settings["episodes"])
    return {
        **observed,
        "tasks": list(range(int(settings["tasks"]))),
        "init_states": list(range(first, first + episodes)),
        "seed": seed,
    }


def _observed(ref: str, fields: dict[str, Any], settings: dict[str, Any]) -> dict[str, Any]:
    """Which components the calibration episodes observe, and what the quantizer does with it."""
    scope_components = SCOPE_COMPONENTS[fields["scope"]]
    if fields["method"] == "awq":  # AWQ's own scale search: no rollout smoothing or clipping
        return {"components": scope_components, "alpha": None, "quantile": None, "sample_rows": AWQ_SAMPLE_ROWS}
    if fields["method"] == "smoothquant":  # SmoothQuant's migration, no clipping
        return {"components": scope_components, "alpha": SMOOTHQUANT_ALPHA, "quantile": None}
    parsed = fields["calibration"]
    if parsed["components"] == "all":
        components = scope_components
    elif parsed["components"] in scope_components:
        components = [parsed["components"]]
    else:
        raise UserError(
            f"cell {ref!r}: calibrates {parsed['components']!r}, which is outside scope {fields['scope']!r}"
        )
    return {
        "components": components,
        "alpha": parsed["alpha"] if parsed["alpha"] is not None else float(settings["alpha"]),
        "quantile": float(settings["quantile"]),
    }


def canonical(cfg: dict[str, Any]) -> dict[str, Any]:
    """A JSON round trip: the exact value that is hashed and written to headers."""
    return json.loads(canonical_json(cfg))


def canonical_json(cfg: dict[str, Any]) -> str:
    return json.dumps(cfg, sort_keys=True, separators=(",", ":"), ensure_ascii=True)


def config_hash(cfg: dict[str, Any]) -> str:
    """12 hex digits of the SHA-256 of the canonical JSON of a cell config."""
    return hashlib.sha256(canonical_json(cfg).encode()).hexdigest()[:12]


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


def study_cells(refs: list[str], study: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Canonical configs of the cells `refs` keyed by config hash (what the rollout rules run)."""
    return {config_hash(cfg): cfg for cfg in (cell_config(ref, study) for ref in refs)}
