"""`vqb rollout REF`: run one cell outside Snakemake, into the folder the workflow would use.

    vqb rollout REF                            # REF <benchmark>/<suite>/<model>/<cell> of the demo study
    vqb rollout REF --config config/paper.yaml --num-envs 8
    vqb rollout REF --show                                                         # config + hash only

Results go to `<checkout>/results/` (the checkout holding this package, as Snakemake would) unless
`--results DIR` names another project folder.

Fetches the checkpoint and collects calibration statistics first when the cell needs them; an
interrupted run resumes from its journal. Ctrl-C (SIGINT) or SIGTERM (SLURM's time limit, `kill`)
prints how many of the cell's episodes are recorded, stops the simulator workers and exits 130 or 143;
the same command resumes the cell. One process writes a cell at a time: a second `vqb rollout`,
Snakemake job or SLURM job of the same cell is refused, naming the first (`runner.lock`). Under
`study.sequential` a cell stops against another cell's records (`runner.stopping`): run that cell first. The config file is validated exactly as Snakemake
validates it (the same schema and validator), and the cell against the registries, before anything runs.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import vlaquantbench
from vlaquantbench.cells import (CalibrationConfig, CellConfig, calibration_config, cell_config, checkpoint_key,
                                 checkpoint_request, config_hash)
from vlaquantbench.config import field_schema, integer_option, load_workflow_config, workflow_config_name
from vlaquantbench.config.study import ExecutionConfig, StudyConfig
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
                        help="simulator worker processes (default: study.execution.num_envs); at most what the "
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
    study = StudyConfig.from_dict(load_workflow_config(args.config).get("study"), workflow_config_name(args.config))
    cfg = cell_config(args.ref, study)
    project = args.results or project_root()
    out = project / CELLS_DIR / config_hash(cfg)
    if args.show:
        print(json.dumps({"config_hash": config_hash(cfg), "folder": str(out), "config": cfg}, indent=2))
        return 0
    from vlaquantbench.records.cell import JOURNAL_FILE
    from vlaquantbench.runner.journal import recorded_keys
    from vlaquantbench.runner.lock import writing
    from vlaquantbench.runner.signals import report_stop, sigterm_interrupts

    # The worker count against the memory available, before anything is written, downloaded or loaded.
    setting = "--num-envs" if args.num_envs is not None else "study.execution.num_envs"
    requested = min(study.execution.num_envs if args.num_envs is None else args.num_envs,
                    len(cfg["tasks"]) * cfg["episodes_per_task"])
    execution = replace(study.execution, num_envs=affordable_workers(requested, cfg["benchmark"], cfg["suite"], setting))
    try:
        # The lock first: a second writer of this cell is refused before it downloads, calibrates or
        # loads anything.
        with sigterm_interrupts(), writing(out, out / JOURNAL_FILE, args.ref):
            recorded_keys(out / JOURNAL_FILE)  # episodes journaled twice differently: refused now, not after a download
            return _run(study, execution, cfg, project)
    except KeyboardInterrupt as stop:
        return report_stop(stop, CellConfig.from_dict(cfg), out, out / JOURNAL_FILE)


def _run(study: StudyConfig, execution: ExecutionConfig, cfg: dict, project: Path) -> int:
    from vlaquantbench.runner.calibration import calibrate
    from vlaquantbench.runner.cell import run_cell
    from vlaquantbench.runner.checkpoint import download_checkpoint
    from vlaquantbench.records.cell import EPISODES_FILE

    against = (cfg.get("sequential") or {}).get("against")
    against_records = None if against is None else project / CELLS_DIR / against["config_hash"] / EPISODES_FILE
    if against_records is not None and not against_records.is_file():
        raise UserError(f"cell {cfg['ref']} stops against {against['ref']} (study.sequential), which has no records yet "
                        f"({against_records}): run `vqb rollout {against['ref']}` first")
    stamp = project / "results" / "checkpoints" / checkpoint_key(cfg) / "checkpoint.json"
    if not stamp.exists():  # as the DAG's checkpoint job: a checkpoint trained here is verified, not fetched
        download_checkpoint(**checkpoint_request(cfg, study), stamp=stamp)
    stats = None
    calib = calibration_config(cfg)
    if calib is not None:
        stats = project / "results" / "calibration" / f"{config_hash(calib)}.pt"
        if not stats.exists():
            calibrate(CalibrationConfig.from_dict(calib), stats, stamp, **execution.calibration_kwargs())
    cell_hash = config_hash(cfg)
    print(run_cell(CellConfig.from_dict(cfg), project / CELLS_DIR / cell_hash, stamp, stats, config_hash=cell_hash, against_records=against_records,
                   **execution.as_kwargs()))
    return 0
