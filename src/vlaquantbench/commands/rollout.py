"""`vqb rollout REF`: run one cell outside Snakemake, into the folder the workflow would use.

    vqb rollout libero/libero_spatial/pi05/ablate-W4A4-ah-onlyself_attn            # demo study
    vqb rollout REF --config config/paper.yaml --num-envs 8
    vqb rollout REF --show                                                         # config + hash only

Results go to `<checkout>/results/` (the checkout holding this package, as Snakemake would) unless
`--results DIR` names another project folder.

Fetches the checkpoint and collects calibration statistics first when the cell needs them; an
interrupted run resumes from its journal. Ctrl-C prints how many of the cell's episodes are recorded
and exits 130; the same command resumes the cell. The config file is validated exactly as Snakemake
validates it (the same schema and validator), and the cell against the registries, before anything runs.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import vlaquantbench
from vlaquantbench.cells import calibration_config, cell_config, checkpoint_key, config_hash
from vlaquantbench.config import field_schema, integer_option, load_workflow_config
from vlaquantbench.config.study import StudyConfig
from vlaquantbench.envs.memory import affordable_workers
from vlaquantbench.errors import UserError
from vlaquantbench.workflow import CELLS_DIR


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("rollout", help="run one cell's closed-loop episodes (resumable)")
    parser.add_argument("ref", help="cell reference <benchmark>/<suite>/<model>/<cell>")
    parser.add_argument("--config", default="config/config.yaml",
                        help="config whose `study` defines the cell; as with `snakemake --configfile`, it is merged "
                             "over config/config.yaml of the current folder")
    parser.add_argument(
        "--results",
        type=Path,
        help="project folder whose results/ receives the cell (default: the checkout holding this package, "
        "where `snakemake` writes; required when the package is not run from a checkout)",
    )
    parser.add_argument("--num-envs", type=integer_option(field_schema("config", "study", "execution", "num_envs")),
                        help="LIBERO worker processes (default: study.execution.num_envs); at most what the "
                             "memory available holds (README: Memory)")
    parser.add_argument("--show", action="store_true", help="print the canonical cell config and its hash, run nothing")
    parser.set_defaults(func=run)


def project_root() -> Path:
    """The checkout this package runs from (the folder of the Snakefile), so that `vqb rollout` and
    `snakemake` share results/ wherever the command is typed."""
    root = Path(vlaquantbench.__file__).resolve().parents[2]
    if not (root / "Snakefile").is_file():
        raise UserError(f"vlaquantbench is not running from a project checkout ({root} has no Snakefile): pass --results DIR")
    return root


def run(args: argparse.Namespace) -> int:
    # The whole file against the schema the Snakefile validates with, then the cell against the
    # registries: a misspelt or unknown key fails here, before any checkpoint or model is touched.
    study = StudyConfig.from_dict(load_workflow_config(args.config).get("study"), args.config)
    cfg = cell_config(args.ref, study)
    project = args.results or project_root()
    out = project / CELLS_DIR / config_hash(cfg)
    if args.show:
        print(json.dumps({"config_hash": config_hash(cfg), "folder": str(out), "config": cfg}, indent=2))
        return 0
    try:
        return _run(args, study, cfg, project)
    except KeyboardInterrupt:
        from vlaquantbench.records.cell import JOURNAL_FILE
        from vlaquantbench.runner.journal import recorded_episodes

        total = len(cfg["tasks"]) * cfg["episodes_per_task"]
        done = recorded_episodes(out / JOURNAL_FILE)
        print(f"\nvqb rollout: interrupted: {args.ref} has {done} of {total} episodes recorded in {out}; "
              "run the same command again to resume it", file=sys.stderr)
        return 130


def _run(args: argparse.Namespace, study: StudyConfig, cfg: dict, project: Path) -> int:
    from vlaquantbench.runner.calibration import calibrate
    from vlaquantbench.runner.cell import run_cell
    from vlaquantbench.runner.checkpoint import download_checkpoint

    execution = study.execution.as_kwargs()
    # The worker count against the memory available, before the checkpoint download and the policy load.
    setting = "--num-envs" if args.num_envs is not None else "study.execution.num_envs"
    requested = min(execution["num_envs"] if args.num_envs is None else args.num_envs, len(cfg["tasks"]) * cfg["episodes_per_task"])
    execution["num_envs"] = affordable_workers(requested, cfg["benchmark"], cfg["suite"], setting)
    stamp = project / "results" / "checkpoints" / checkpoint_key(cfg) / "checkpoint.json"
    if not stamp.exists():
        download_checkpoint(**{k: cfg[k] for k in ("model", "variant", "checkpoint", "revision")}, stamp=stamp)
    stats = None
    calib = calibration_config(cfg)
    if calib is not None:
        stats = project / "results" / "calibration" / f"{config_hash(calib)}.pt"
        if not stats.exists():
            calibrate(calib, stats, stamp, **execution)
    print(run_cell(cfg, project / CELLS_DIR / config_hash(cfg), stamp, stats, **execution))
    return 0
