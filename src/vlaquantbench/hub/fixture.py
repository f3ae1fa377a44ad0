"""`vqb hub-fixture DIR`: a Hugging Face cache (`HF_HOME` layout) holding the study's checkpoints
under their real repository ids and pinned revisions, small enough to load on a CPU in seconds.

Each model that has one registers its fixture in its own folder
(`vlaquantbench.models.<model>.hub_fixture.FIXTURE`, a `HubFixture`): the repositories of the
tokenizers its processors load (written first, at a revision derived from their files, with
`refs/main` pointing there, since lerobot loads them by name) and a writer of the checkpoint's
files, or, for a model released as one repository per suite (OpenVLA-OFT), a writer per released
repository with its pinned revision. The config's checkpoint goes into the cache at the revision the
config pins; a model's other released repositories at their own.
"""

from __future__ import annotations

import importlib
import importlib.util
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from vlaquantbench.errors import UserError
from vlaquantbench.hub.cache import offline_cache, tree_revision, write_snapshot


CheckpointWriter = Callable[[Path, int], None]  # (folder, seed) -> the checkpoint's files in folder


@dataclass(frozen=True)
class HubFixture:
    write_checkpoint: CheckpointWriter | None = None  # whichever repository the config names
    tokenizers: dict[str, Callable[[Path], Path]] = field(default_factory=dict)  # repo id -> writer
    releases: dict[str, tuple[str, CheckpointWriter]] = field(default_factory=dict)  # repo id -> (revision, writer)

    def repositories(self, model: str, checkpoint: str, revision: str) -> dict[str, tuple[str, CheckpointWriter]]:
        """{repo id: (revision, writer)} to write for a config that pins `checkpoint` at `revision`."""
        repos = dict(self.releases)
        if checkpoint in repos:
            repos[checkpoint] = (revision, repos[checkpoint][1])
        elif self.write_checkpoint is not None:
            repos[checkpoint] = (revision, self.write_checkpoint)
        else:
            raise UserError(f"study.models.{model}: checkpoint {checkpoint!r} is none of the released repositories "
                            f"the hub fixture writes ({', '.join(repos)})")
        return repos


def fixture_module(model: str) -> str:
    return f"vlaquantbench.models.{model}.hub_fixture"


def get_fixture(model: str) -> HubFixture:
    name = fixture_module(model)
    if importlib.util.find_spec(f"vlaquantbench.models.{model}") is None or importlib.util.find_spec(name) is None:
        raise UserError(f"model {model!r} has no hub fixture (a FIXTURE in {name})")
    return importlib.import_module(name).FIXTURE


def full_variant_models(study: dict) -> dict[str, dict]:
    """`study.models` entries that load a released checkpoint: {model: {checkpoint, revision}}."""
    models = {}
    for model, entry in (study.get("models") or {}).items():
        if entry.get("variant", "full") != "full":
            continue
        if not entry.get("checkpoint") or not entry.get("revision"):
            raise UserError(f"study.models.{model}: a full-variant model needs `checkpoint` and a pinned `revision`")
        models[model] = {"checkpoint": entry["checkpoint"], "revision": entry["revision"]}
    return models


def build_hub_fixture(hf_home: str | Path, models: dict[str, dict], seed: int = 0) -> dict[str, dict]:
    """Write the fixture of every model in `models` ({model: {checkpoint, revision}}) into
    `<hf_home>/hub`; returns {repo id: {revision, path}} of every repository written."""
    if not models:
        raise UserError("no full-variant model to build a hub fixture for")
    fixtures = {model: get_fixture(model) for model in models}  # refuse unknown models first
    checkpoints = {repo_id: entry for model, fixture in fixtures.items()
                   for repo_id, entry in fixture.repositories(model, **models[model]).items()}
    hub = Path(hf_home) / "hub"
    written: dict[str, dict] = {}
    with offline_cache(hf_home), tempfile.TemporaryDirectory() as scratch:
        for repo_id, write in {r: w for f in fixtures.values() for r, w in f.tokenizers.items()}.items():
            folder = write(Path(scratch) / repo_id)
            revision = tree_revision(folder)
            written[repo_id] = {"revision": revision, "path": str(write_snapshot(hub, repo_id, revision, folder))}
        for repo_id, (revision, write) in checkpoints.items():
            folder = Path(scratch) / repo_id
            write(folder, seed)
            written[repo_id] = {"revision": revision, "path": str(write_snapshot(hub, repo_id, revision, folder))}
    return written
