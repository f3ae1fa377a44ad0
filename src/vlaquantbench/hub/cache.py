"""A repository snapshot written into a Hugging Face cache exactly as huggingface_hub lays it out.

    <HF_HOME>/hub/models--<org>--<name>/
        blobs/<etag>                       file contents, named by their etag
        snapshots/<revision>/<path>        relative symlinks into blobs/
        refs/<ref>                         the commit a branch name resolves to

The hub's etag of a Git-LFS file (weights, tokenizer models) is its SHA-256; of any other file the
Git blob SHA-1 of its bytes. huggingface_hub resolves a commit revision through `snapshots/` and a
branch through `refs/`, offline (`HF_HUB_OFFLINE=1`, `local_files_only=True`) as online. The tree
listing huggingface_hub >= 1.3 also caches is not written: its writer is private, and lookups with
`local_files_only` (the project's offline path, `runner.checkpoint`) do not read it.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
from pathlib import Path

# Suffixes the hub stores in Git LFS (its default .gitattributes), plus tokenizer.json, which the
# tokenizer repositories track in LFS too.
LFS_SUFFIXES = (".safetensors", ".bin", ".model", ".pt", ".pth", ".msgpack", ".h5", ".gguf")
LFS_NAMES = ("tokenizer.json",)


def repo_folder(hub_cache: str | Path, repo_id: str, repo_type: str = "model") -> Path:
    """`models--<org>--<name>` (huggingface_hub's `repo_folder_name`)."""
    from huggingface_hub.file_download import repo_folder_name

    return Path(hub_cache) / repo_folder_name(repo_id=repo_id, repo_type=repo_type)


def _is_lfs(path: Path) -> bool:
    return path.suffix in LFS_SUFFIXES or path.name in LFS_NAMES


def _git_blob_id(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


def etag(path: Path) -> str:
    data = path.read_bytes()
    return hashlib.sha256(data).hexdigest() if _is_lfs(path) else _git_blob_id(data)


def write_snapshot(hub_cache: str | Path, repo_id: str, revision: str, files: Path, ref: str | None = "main") -> Path:
    """Put every file below folder `files` into the cache as `repo_id` at commit `revision`; point
    branch `ref` at it (None: no branch). Returns the snapshot folder."""
    repo = repo_folder(hub_cache, repo_id)
    snapshot = repo / "snapshots" / revision
    if snapshot.exists():
        shutil.rmtree(snapshot)
    sources = sorted(p for p in Path(files).rglob("*") if p.is_file())
    for source in sources:
        relative = source.relative_to(files)
        blob = repo / "blobs" / etag(source)
        blob.parent.mkdir(parents=True, exist_ok=True)
        if not blob.exists():
            shutil.copyfile(source, blob)
        link = snapshot / relative
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(os.path.relpath(blob, link.parent))
    if ref is not None:
        (repo / "refs").mkdir(parents=True, exist_ok=True)
        (repo / "refs" / ref).write_text(revision)
    return snapshot


def tree_revision(files: Path) -> str:
    """A commit id for a repository that has none to pin (40 hex digits from its file etags)."""
    listing = "".join(f"{p.relative_to(files)}\0{etag(p)}\n" for p in sorted(Path(files).rglob("*")) if p.is_file())
    return hashlib.sha1(listing.encode()).hexdigest()


@contextlib.contextmanager
def offline_cache(hf_home: str | Path):
    """Resolve every hub lookup of this process from `<hf_home>/hub`, offline: what `HF_HOME=DIR
    HF_HUB_OFFLINE=1` does for a fresh process (huggingface_hub reads both constants per call)."""
    from huggingface_hub import constants

    saved = constants.HF_HUB_CACHE, constants.HF_HUB_OFFLINE
    constants.HF_HUB_CACHE, constants.HF_HUB_OFFLINE = str(Path(hf_home) / "hub"), True
    try:
        yield
    finally:
        constants.HF_HUB_CACHE, constants.HF_HUB_OFFLINE = saved
