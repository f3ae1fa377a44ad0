"""Checkpoint download at a pinned revision (huggingface_hub), recorded in a small stamp file.

The stamp (`checkpoint.json`) is what the rollout rules depend on: it names the checkpoint, the
revision and the local folder holding the snapshot. The demo variant has random weights and no
checkpoint to fetch; its stamp says so, so the DAG has the same shape for both.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from vlaquantbench.atomic import write_text
from vlaquantbench.errors import UserError


def download_checkpoint(model: str, variant: str, checkpoint: str | None, revision: str | None, stamp: Path) -> dict:
    """Fetch `checkpoint` at `revision` next to `stamp` and write the stamp.

    Raises UserError naming the checkpoint when the hub cannot be reached or the revision is
    unknown, instead of a traceback from inside the HTTP client.
    """
    stamp = Path(stamp)
    info: dict[str, Any] = {"model": model, "variant": variant, "checkpoint": checkpoint, "revision": revision}
    if variant in ("demo", "random"):  # random weights: nothing to fetch
        info["path"] = None
    else:
        if not checkpoint or not revision:
            raise UserError(f"study.models.{model}: a full-variant model needs `checkpoint` and a pinned `revision`")
        import httpx
        from huggingface_hub import snapshot_download
        from huggingface_hub.errors import HfHubHTTPError, LocalEntryNotFoundError

        local_dir = stamp.parent / stamp.stem
        try:
            path = snapshot_download(checkpoint, revision=revision, local_dir=local_dir)
        except (LocalEntryNotFoundError, HfHubHTTPError, httpx.HTTPError, OSError) as err:
            reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise UserError(
                f"cannot download checkpoint {checkpoint}@{revision}: {reason} "
                "(the Hugging Face hub is unreachable or the revision does not exist; "
                "download it elsewhere and copy it to " + str(local_dir) + ")"
            ) from None
        info["path"] = str(Path(path).resolve())
    write_text(stamp, json.dumps(info, indent=2, sort_keys=True) + "\n")
    return info
