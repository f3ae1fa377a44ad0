"""Checkpoint download at a pinned revision (huggingface_hub), recorded in a small stamp file.

The stamp (`checkpoint.json`) is what the rollout rules depend on: it names the checkpoint, the
revision and the snapshot folder in the Hugging Face cache (`HF_HOME`), plus the tokenizer
repositories the checkpoint's preprocessor loads by name, fetched too so that no rollout has to.
With `HF_HUB_OFFLINE=1` everything resolves from the cache, e.g. the fixture of `vqb hub-fixture`.
The demo variant has random weights and no checkpoint to fetch; its stamp says so, so the DAG has
the same shape for both.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from vlaquantbench.atomic import write_text
from vlaquantbench.errors import UserError

# What a tokenizer repository is fetched for: transformers' tokenizer files and the model config
# AutoTokenizer reads its model type from (not the model's weights).
TOKENIZER_PATTERNS = ["tokenizer*", "special_tokens_map.json", "added_tokens.json", "config.json"]


def _snapshot(what: str, repo_id: str, revision: str | None, allow_patterns: list[str] | None = None) -> Path:
    """`repo_id` at `revision` in the HF cache (fetched unless offline); UserError naming the revision
    and the revisions the cache holds, instead of a traceback from inside the HTTP client."""
    import httpx
    from huggingface_hub import constants, snapshot_download
    from huggingface_hub.errors import HfHubHTTPError, LocalEntryNotFoundError

    from vlaquantbench.hub.cache import repo_folder

    try:
        # Offline, only the cache's snapshots/ and refs/ are consulted (caches written before
        # huggingface_hub kept tree listings resolve too).
        path = snapshot_download(repo_id, revision=revision, allow_patterns=allow_patterns,
                                 local_files_only=constants.HF_HUB_OFFLINE)
        return Path(path).absolute()
    except (LocalEntryNotFoundError, HfHubHTTPError, httpx.HTTPError, OSError) as err:
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        snapshots = repo_folder(constants.HF_HUB_CACHE, repo_id) / "snapshots"
        held = sorted(p.name for p in snapshots.iterdir()) if snapshots.is_dir() else []
        raise UserError(
            f"cannot download {what} {repo_id}@{revision or 'main'}: {reason} (cache {constants.HF_HUB_CACHE} holds "
            f"{'revisions ' + ', '.join(held) if held else 'no revision of it'}; offline: {constants.HF_HUB_OFFLINE}). "
            "Fetch the pinned revision where the hub is reachable into this HF_HOME, or pin a revision it holds."
        ) from None


def download_checkpoint(model: str, variant: str, checkpoint: str | None, revision: str | None, stamp: Path) -> dict:
    """Resolve `checkpoint` at `revision` (and its tokenizers) in the HF cache and write the stamp."""
    stamp = Path(stamp)
    info: dict[str, Any] = {"model": model, "variant": variant, "checkpoint": checkpoint, "revision": revision}
    if variant in ("demo", "random"):  # random weights: nothing to fetch
        info["path"] = None
    else:
        from vlaquantbench.hub.checks import PROCESSOR_FILES, check_snapshot_revision, tokenizer_names

        if not checkpoint or not revision:
            raise UserError(f"study.models.{model}: a full-variant model needs `checkpoint` and a pinned `revision`")
        path = _snapshot("checkpoint", checkpoint, revision)
        check_snapshot_revision(path, checkpoint, revision)
        info["path"] = str(path)
        # A lerobot checkpoint's preprocessor names the tokenizer repositories it loads; a release
        # without lerobot processors (X-VLA's) carries its tokenizer in its own snapshot.
        named = tokenizer_names(path) if (path / PROCESSOR_FILES[0]).exists() else []
        info["tokenizers"] = {name: _snapshot("tokenizer", name, None, TOKENIZER_PATTERNS).name for name in named}
    write_text(stamp, json.dumps(info, indent=2, sort_keys=True) + "\n")
    return info
