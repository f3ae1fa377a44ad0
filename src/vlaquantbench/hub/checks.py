"""What a checkpoint snapshot must pass before any rollout, and the provenance the cell header records.

lerobot's loaders forgive too much for a benchmark: `PI0xPolicy.from_pretrained` prints a warning
and returns randomly initialised weights when the state dict does not load, and a normalizer step
whose statistics lack a feature leaves that feature unnormalized. These checks turn each such case
into a UserError naming the file or revision.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from vlaquantbench.errors import UserError

PROCESSOR_FILES = ("policy_preprocessor.json", "policy_postprocessor.json")
NORMALIZER_STEPS = ("normalizer_processor", "unnormalizer_processor")
# The statistics each lerobot NormalizationMode reads (lerobot.processor.normalize_processor).
MODE_STATS = {"MEAN_STD": ("mean", "std"), "MIN_MAX": ("min", "max"), "QUANTILES": ("q01", "q99"),
              "QUANTILE10": ("q10", "q90")}
# Files of a tokenizer repository that transformers reads, where present.
TOKENIZER_FILES = ("tokenizer.json", "tokenizer_config.json", "special_tokens_map.json", "added_tokens.json",
                   "tokenizer.model", "config.json")


def sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def check_snapshot_revision(folder: str | Path, checkpoint: str, revision: str) -> None:
    """A cache snapshot is `snapshots/<commit>`: refuse one whose commit is not the pinned revision."""
    found = Path(folder).name
    if found != revision:
        raise UserError(
            f"checkpoint {checkpoint}: the snapshot {folder} is revision {found}, but the config pins revision "
            f"{revision}; fetch the pinned revision (its download rule) or change study.models' revision"
        )


def load_json(path: Path, what: str) -> Any:
    """The JSON file `path`; UserError naming it (as `what`) when it is missing or not JSON."""
    if not path.is_file():
        raise UserError(f"{what} {path.name} is missing from {path.parent}")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise UserError(f"{what} {path} is corrupt (not JSON: {err})") from None


def _load_state(path: Path) -> dict:
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    if not path.is_file():
        raise UserError(f"normalizer state file {path.name} named by its processor is missing from {path.parent}")
    try:
        return load_file(path)
    except (SafetensorError, OSError, ValueError) as err:
        raise UserError(f"normalizer state file {path} is corrupt ({err})") from None


def _check_statistics(path: Path, config: dict, state: Mapping[str, Any]) -> None:
    """Every feature a normalizer step normalizes has the statistics its mode reads, finite and of the feature's size."""
    for key, feature in config.get("features", {}).items():
        mode = config.get("norm_map", {}).get(feature["type"], "IDENTITY")
        for stat in MODE_STATS.get(mode, ()):
            value = state.get(f"{key}.{stat}")
            if value is None:
                raise UserError(f"normalizer state file {path} lacks {key}.{stat}, which {mode} normalization of {key} reads")
            if value.shape[-1:] != tuple(feature["shape"][-1:]) or not bool(value.isfinite().all()):
                raise UserError(f"normalizer state file {path}: {key}.{stat} has shape {tuple(value.shape)} or non-finite "
                                f"values; feature {key} has shape {tuple(feature['shape'])}")


def check_processors(folder: str | Path) -> dict:
    """Check the processor files and their normalizer state files; returns the header's `normalization`
    record: each processor file and state file with its sha256, and the normalization modes."""
    folder = Path(folder)
    record: dict[str, Any] = {}
    for name in PROCESSOR_FILES:
        path = folder / name
        pipeline = load_json(path, "processor file")
        entry: dict[str, Any] = {"file": name, "sha256": sha256(path), "state_files": {}}
        for step in pipeline.get("steps", []):
            if step.get("registry_name") not in NORMALIZER_STEPS:
                continue
            if not step.get("state_file"):
                raise UserError(f"processor file {path}: its {step['registry_name']} step names no state_file")
            state_path = folder / step["state_file"]
            _check_statistics(state_path, step.get("config", {}), _load_state(state_path))
            entry["state_files"][step["state_file"]] = sha256(state_path)
            entry["norm_map"] = step.get("config", {}).get("norm_map")
        record[name.removesuffix(".json")] = entry
    return record


def tokenizer_names(folder: str | Path) -> list[str]:
    """The tokenizer repositories the checkpoint's preprocessor loads by name."""
    steps = load_json(Path(folder) / PROCESSOR_FILES[0], "processor file").get("steps", [])
    return [s["config"]["tokenizer_name"] for s in steps if s.get("config", {}).get("tokenizer_name")]


def load_tokenizer(repo_id: str) -> tuple[Any, dict]:
    """The tokenizer `repo_id` as lerobot's tokenizer step loads it (`AutoTokenizer`), and its
    provenance: class, source repository, the revision the cache resolved and each file's sha256."""
    from huggingface_hub import try_to_load_from_cache
    from transformers import AutoTokenizer

    try:
        tokenizer = AutoTokenizer.from_pretrained(repo_id)
    except Exception as err:  # transformers raises OSError, ValueError, KeyError, JSON errors ...
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise UserError(f"tokenizer {repo_id} (named by {PROCESSOR_FILES[0]}) does not load: {reason}") from None
    files = {name: try_to_load_from_cache(repo_id, name) for name in TOKENIZER_FILES}
    files = {name: Path(path) for name, path in files.items() if isinstance(path, str)}
    revisions = {path.parent.name for path in files.values()}
    return tokenizer, {
        "class": type(tokenizer).__name__,
        "repo": repo_id,
        "revision": revisions.pop() if len(revisions) == 1 else sorted(revisions),
        "files": {name: sha256(path) for name, path in sorted(files.items())},
    }


def load_snapshot_tokenizer(tokenizer_class: type, folder: str | Path, checkpoint: str, files: tuple[str, ...]) -> tuple[Any, dict]:
    """A tokenizer a release carries in its own snapshot, read with `tokenizer_class` from `folder`
    (named `files`, the first three in messages), and its provenance: class, repository, the
    snapshot's revision and the sha256 of each of `files` present."""
    folder = Path(folder)
    try:
        tokenizer = tokenizer_class.from_pretrained(folder, local_files_only=True)
    except Exception as err:  # transformers raises OSError, ValueError, KeyError, JSON errors ...
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise UserError(f"tokenizer of {checkpoint} ({', '.join(files[:3])} in {folder}) does not load: {reason}") from None
    hashes = {name: sha256(folder / name) for name in files if (folder / name).is_file()}
    return tokenizer, {"class": type(tokenizer).__name__, "repo": checkpoint, "revision": folder.name, "files": hashes}


def weight_shapes(path: str | Path) -> dict[str, tuple[int, ...]]:
    """Tensor names and shapes of a safetensors file, read from its header only."""
    from safetensors import SafetensorError, safe_open

    path = Path(path)
    if not path.is_file():
        raise UserError(f"weights file {path.name} is missing from {path.parent}")
    try:
        with safe_open(path, "pt") as f:
            return {k: tuple(f.get_slice(k).get_shape()) for k in f.keys()}
    except (SafetensorError, OSError, ValueError) as err:
        raise UserError(f"weights file {path} is corrupt ({err})") from None


def check_state_dict_fits(found: Mapping[str, tuple], expected: Mapping[str, tuple], source: str | Path) -> None:
    """Refuse a state dict whose keys or shapes differ from the architecture's."""
    missing = sorted(set(expected) - set(found))
    unexpected = sorted(set(found) - set(expected))
    wrong = sorted(k for k in set(found) & set(expected) if tuple(found[k]) != tuple(expected[k]))
    if missing or unexpected or wrong:
        def some(keys):
            return ", ".join(keys[:3]) + (f" (+{len(keys) - 3} more)" if len(keys) > 3 else "")

        problems = [f"{len(missing)} missing keys: {some(missing)}" if missing else "",
                    f"{len(unexpected)} unexpected keys: {some(unexpected)}" if unexpected else "",
                    "wrong shapes: " + some([f"{k} {tuple(found[k])} vs {tuple(expected[k])}" for k in wrong]) if wrong else ""]
        raise UserError(f"state dict {source} does not fit the architecture: " + "; ".join(p for p in problems if p))
