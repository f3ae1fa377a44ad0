"""Checkpoint download at a pinned revision (huggingface_hub), recorded in a small stamp file.

The stamp (`checkpoint.json`) is what the rollout rules depend on: it names the checkpoint, the
revision and the snapshot folder in the Hugging Face cache (`HF_HOME`), plus the tokenizer
repositories the checkpoint's preprocessor loads by name, fetched too so that no rollout has to.
A checkpoint trained here is no download: its folder (`models.trained_home`) is verified against its
training.json and the stamp names its policy folder.
With `HF_HUB_OFFLINE=1` everything resolves from the cache, e.g. the fixture of `vqb hub-fixture`.
The demo variant has random weights and no checkpoint to fetch; its stamp says so, so the DAG has
the same shape for both.

Every request has a timeout and a snapshot a bounded number of attempts: huggingface_hub bounds its
file transfers by `HF_HUB_DOWNLOAD_TIMEOUT` / `HF_HUB_ETAG_TIMEOUT` (seconds, default 10) but sends
the revision lookup and the file listing with no timeout at all, so a server that accepts the
connection and never answers held the download until it was killed. Each snapshot is tried
`DOWNLOAD_ATTEMPTS` times (an interrupted one resumes its partial files), then refused naming the
repository and revision.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vlaquantbench.atomic import write_text
from vlaquantbench.config import validate
from vlaquantbench.errors import UserError
from vlaquantbench.textfiles import read_parsed
from vlaquantbench.models.registry import get_model_spec

DOWNLOAD_ATTEMPTS = 3
# Between attempts: 2 s, then 4 s (tenacity's exponential wait), time for a passing hub hiccup.
RETRY_WAIT_S = 2


@dataclass(frozen=True)
class CheckpointStamp:
    """A checkpoint stamp, read once by the job that loads the policy (`runner.cell.load_policy`); the
    stamp file satisfies `schemas/checkpoint_stamp.schema.yaml`, checked when it is written and read."""

    model: str
    variant: str
    checkpoint: str | None
    revision: str | None
    path: str | None  # the snapshot folder in the HF cache (trained here: its policy folder); None: random weights
    trained_home: str | None = None  # a checkpoint trained here: its folder (`models.trained_home`)
    tokenizers: dict[str, str] | None = None  # tokenizer repository -> the revision fetched for it

    @classmethod
    def read(cls, stamp: str | Path) -> CheckpointStamp:
        """The stamp at `stamp`; UserError naming the file and the field when it is not a stamp."""
        return cls(**validate(read_parsed(Path(stamp), json.loads, "JSON"), "checkpoint_stamp", str(stamp)))


def _bound_timeouts(request) -> None:
    """An httpx request hook: every timeout huggingface_hub left unbounded becomes HF_HUB_DOWNLOAD_TIMEOUT."""
    from huggingface_hub import constants

    timeouts = request.extensions.get("timeout", {})
    request.extensions["timeout"] = {k: constants.HF_HUB_DOWNLOAD_TIMEOUT if v is None else v for k, v in timeouts.items()}


def _bounded_client():
    """huggingface_hub's own client (its request hooks and redirects), every request timed out."""
    # Its default factory is private (huggingface_hub 1.33), but rebuilding the client by hand would
    # copy its private request hook; the public seam, set_client_factory, replaces the factory whole.
    from huggingface_hub.utils import _http

    client = _http.default_client_factory()
    client.event_hooks = {**client.event_hooks, "request": [*client.event_hooks["request"], _bound_timeouts]}
    return client


def _transient(err: BaseException) -> bool:
    """A network failure worth another attempt: a timeout or a dropped connection, raised as such or
    behind huggingface_hub's "cannot find it locally" (its revision lookup swallows them)."""
    import httpx

    while err is not None:
        if isinstance(err, (httpx.TimeoutException, httpx.NetworkError, httpx.RemoteProtocolError)):
            return True
        err = err.__cause__
    return False


# What a tokenizer repository is fetched for: transformers' tokenizer files and the model config
# AutoTokenizer reads its model type from (not the model's weights).
TOKENIZER_PATTERNS = ["tokenizer*", "special_tokens_map.json", "added_tokens.json", "config.json"]


def _snapshot(what: str, repo_id: str, revision: str | None, allow_patterns: list[str] | None = None) -> Path:
    """`repo_id` at `revision` in the HF cache (fetched unless offline); UserError naming the revision
    and the revisions the cache holds, instead of a traceback from inside the HTTP client."""
    import httpx
    import tenacity
    from huggingface_hub import constants, set_client_factory, snapshot_download
    from huggingface_hub.errors import HfHubHTTPError, LocalEntryNotFoundError

    from vlaquantbench.hub.cache import repo_folder

    set_client_factory(_bounded_client)  # huggingface_hub's seam for configuring its HTTP client
    attempts = tenacity.Retrying(
        stop=tenacity.stop_after_attempt(DOWNLOAD_ATTEMPTS), wait=tenacity.wait_exponential(multiplier=RETRY_WAIT_S),
        retry=tenacity.retry_if_exception(_transient), reraise=True,
    )
    try:
        # Offline, only the cache's snapshots/ and refs/ are consulted (caches written before
        # huggingface_hub kept tree listings resolve too).
        path = attempts(snapshot_download, repo_id, revision=revision, allow_patterns=allow_patterns,
                        local_files_only=constants.HF_HUB_OFFLINE)
        return Path(path).absolute()
    except (LocalEntryNotFoundError, HfHubHTTPError, httpx.HTTPError, OSError) as err:
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        if _transient(err):
            tries = attempts.statistics.get("attempt_number", DOWNLOAD_ATTEMPTS)
            reason = (f"no answer within HF_HUB_DOWNLOAD_TIMEOUT={constants.HF_HUB_DOWNLOAD_TIMEOUT} s from "
                      f"{constants.ENDPOINT} in {tries} attempts ({reason})")
        snapshots = repo_folder(constants.HF_HUB_CACHE, repo_id) / "snapshots"
        held = sorted(p.name for p in snapshots.iterdir()) if snapshots.is_dir() else []
        raise UserError(
            f"cannot download {what} {repo_id}@{revision or 'main'}: {reason} (cache {constants.HF_HUB_CACHE} holds "
            f"{'revisions ' + ', '.join(held) if held else 'no revision of it'}; offline: {constants.HF_HUB_OFFLINE}). "
            "Fetch the pinned revision where the hub is reachable into this HF_HOME, or pin a revision it holds."
        ) from None


def download_checkpoint(model: str, variant: str, checkpoint: str | None, revision: str | None, stamp: Path,
                        trained_home: str | None = None) -> dict:
    """Resolve `checkpoint` at `revision` (and its tokenizers) in the HF cache and write the stamp; with
    `trained_home` (a checkpoint trained here), verify that folder instead and name its policy folder."""
    if trained_home is None:
        return _resolve(model, variant, checkpoint, revision, Path(stamp))
    from vlaquantbench.models import trained_home as home

    training = home.verify(trained_home, f"study.models.{model}.trained")
    if (training["checkpoint"], training["revision"]) != (checkpoint, revision):
        raise UserError(f"study.models.{model}.trained: {trained_home} holds {training['checkpoint']}@"
                        f"{training['revision']}, not the {checkpoint}@{revision} the cells were planned with: "
                        "the folder changed since the DAG was built; run again")
    info = {"model": model, "variant": variant, "checkpoint": checkpoint, "revision": revision,
            "trained_home": str(Path(trained_home).absolute()),
            "path": str(home.policy_folder(trained_home).absolute()),
            "tokenizers": {training["tokenizer"]["repo"]: training["tokenizer"]["revision"]}}
    return _write_stamp(info, Path(stamp))


def _resolve(model: str, variant: str, checkpoint: str | None, revision: str | None, stamp: Path) -> dict:
    info: dict[str, Any] = {"model": model, "variant": variant, "checkpoint": checkpoint, "revision": revision}
    if variant in ("demo", "random") or not get_model_spec(model).components:  # random weights, or no network
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
    return _write_stamp(info, stamp)


def _write_stamp(info: dict[str, Any], stamp: Path) -> dict:
    validate(info, "checkpoint_stamp", str(stamp))
    write_text(stamp, json.dumps(info, indent=2, sort_keys=True) + "\n")
    return info
