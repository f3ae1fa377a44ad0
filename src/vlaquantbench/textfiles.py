"""Read a text file through a parser, with errors that name the file (the config loader's YAML, a cell's
JSON header)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from vlaquantbench.errors import UserError


def read_parsed(path: str | Path, parse: Callable[[str], Any], kind: str,
                errors: tuple[type[Exception], ...] = (ValueError,)) -> Any:
    """`parse(text of path)`; UserError `<path>: no such file` or `<path>: not valid <kind> (<why>)`
    when it raises one of `errors` (json's JSONDecodeError is a ValueError)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    try:
        return parse(path.read_text())
    except errors as err:
        raise UserError(f"{path}: not valid {kind} ({err})") from None
