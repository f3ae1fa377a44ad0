"""The `vqb` command line.

Each module in `vlaquantbench.commands` that defines `register(subparsers)` contributes one
sub-command; `register` adds a parser and sets `func` on it (a callable taking the parsed args
and returning an exit code). Discovery keeps the sub-commands independent of one another.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from vlaquantbench import __version__, commands
from vlaquantbench.errors import UserError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vqb", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"vlaquantbench {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True)
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        if hasattr(module, "register"):
            module.register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UserError as err:
        print(f"vqb {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
