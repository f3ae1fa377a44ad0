"""`vqb manifest RECORDS_DIR -o FILE`: list record files with episodes, successes and SHA-256."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("manifest", help="write (or --check) a TSV manifest of a records folder")
    parser.add_argument("records_dir", help="folder of cell records (authors' .jsonl or cell folders)")
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("-o", "--output", help="manifest TSV to write")
    group.add_argument("--check", metavar="MANIFEST", help="verify the records against this manifest instead")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vlaquantbench.manifest import verify_manifest, write_manifest  # pandas: only when it runs

    if args.check:
        rows = verify_manifest(args.check, args.records_dir)
        print(f"{len(rows)} record files match {args.check}")
    else:
        print(write_manifest(args.records_dir, args.output))
    return 0
