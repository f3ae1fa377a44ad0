"""Errors that carry a message meant for the user."""

from collections.abc import Mapping
from typing import TypeVar

T = TypeVar("T")


class UserError(Exception):
    """Bad input (a config field, a pattern, a file): shown as one clear line, no traceback.

    Raise it before any expensive work starts, and name the offending field, pattern or file.
    """


def lookup(table: Mapping[str, T], name: str, what: str) -> T:
    """`table[name]`, or UserError `unknown <what> '<name>'; known: <sorted names>` (every registry's lookup)."""
    if name not in table:
        raise UserError(f"unknown {what} {name!r}; known: {', '.join(sorted(table)) or 'none'}")
    return table[name]
