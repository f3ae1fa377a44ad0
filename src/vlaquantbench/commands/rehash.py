"""`vqb rehash RECORDS_DIR... [--manifest RECORDS_DIR=FILE ...]`: rewrite recorded cell headers to the current
canonical config and config hash (`vlaquantbench.rehash`), then their manifests."""

from __future__ import annotations

import argparse
from pathlib import Path


def _manifest(value: str) -> tuple[str, str]:
    records_dir, sep, manifest = value.partition("=")
    if not sep or not records_dir or not manifest:
        raise argparse.ArgumentTypeError(f"{value!r} is not RECORDS_DIR=MANIFEST")
    return records_dir, manifest


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("rehash", help="rewrite recorded cell headers to the current canonical config and "
                                                  "hash, and their manifests")
    parser.add_argument("records_dirs", nargs="+", metavar="RECORDS_DIR",
                        help="folders of cell records, rewritten together (a sequential cell's against cell must be among them)")
    parser.add_argument("--manifest", type=_manifest, action="append", default=[], metavar="RECORDS_DIR=MANIFEST",
                        help="rewrite MANIFEST (vqb manifest) from RECORDS_DIR once its headers are rewritten")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vlaquantbench.errors import UserError
    from vlaquantbench.manifest import write_manifest  # pandas: only when it runs
    from vlaquantbench.rehash import rehash

    given = {str(Path(d)) for d in args.records_dirs}
    unknown = [d for d, _ in args.manifest if str(Path(d)) not in given]
    if unknown:
        raise UserError(f"--manifest {unknown[0]}=...: {unknown[0]} is not one of the RECORDS_DIR arguments")
    for cell in rehash(args.records_dirs):
        print(f"{cell.ref}: {cell.old_hash} -> {cell.new_hash} ({cell.header})")
    for records_dir, manifest in args.manifest:
        print(write_manifest(records_dir, manifest))
    return 0
