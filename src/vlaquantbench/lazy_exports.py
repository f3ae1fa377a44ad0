"""PEP 562 lazy exports: a package names what it exports and from which submodule; each is imported
on first access, so importing the package loads none of its heavy submodules (torch, pandas)."""

import importlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any


def lazy_exports(package: str, submodules: Mapping[str, Sequence[str]]) -> Callable[[str], Any]:
    """The module-level `__getattr__` of `package`, exporting the names each of its `submodules` lists."""
    exports = {name: module for module, names in submodules.items() for name in names}

    def __getattr__(name: str) -> Any:
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{exports[name]}"), name)

    return __getattr__
