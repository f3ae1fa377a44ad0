"""`vqb hub-fixture DIR`: write an offline Hugging Face cache holding the study's released
checkpoints (reduced widths, real layout, real repository ids and pinned revisions), e.g.

    vqb hub-fixture /tmp/hf --config config/paper_smoke.yaml
    HF_HOME=/tmp/hf HF_HUB_OFFLINE=1 snakemake --cores 2 tables/lattice.tex --configfile config/paper_smoke.yaml
"""

from __future__ import annotations

import argparse
import json

from vlaquantbench.config import integer_option, load_workflow_config


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("hub-fixture", help="write an offline HF cache of the study's checkpoints")
    parser.add_argument("dir", help="the cache root (use it as HF_HOME)")
    parser.add_argument("--config", default="config/paper.yaml", help="config whose study.models pin the checkpoints")
    parser.add_argument("--seed", type=integer_option({"type": "integer", "minimum": 0}), default=0,
                        help="seed of the random weights and statistics (>= 0)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vlaquantbench.hub.fixture import build_hub_fixture, full_variant_models

    study = load_workflow_config(args.config).get("study") or {}  # validated as Snakemake validates it
    written = build_hub_fixture(args.dir, full_variant_models(study), seed=args.seed)
    print(json.dumps(written, indent=2))
    return 0
