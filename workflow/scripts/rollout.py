"""Rule rollout: one cell's closed-loop episodes -> header.json + episodes.parquet in the cell's folder (resumes
the cell's journal beside them, which the rule declares as a log: Snakemake keeps a failed job's logs)."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from pathlib import Path

from vlaquantbench.cells import CellConfig
from vlaquantbench.runner.cell import run_cell
from vlaquantbench.runner.gpus import job_gpu
from vlaquantbench.runner.signals import report_stop, sigterm_interrupts
from vlaquantbench.rule_log import job_log

out = Path(snakemake.output.header).parent
cell = CellConfig.from_dict(snakemake.params.cell)
journal = snakemake.params.state["journal"]
# SLURM sends SIGTERM at a job's time limit and on preemption: the job ends as `vqb rollout` does, saying
# how far the cell got (on the job's stderr), its workers closed and its journal whole, with status 143.
try:
    with sigterm_interrupts(), job_log(snakemake), job_gpu(snakemake.params.gpu_slots, f"rollout {cell.ref}"):
        run_cell(
            cell,
            out,
            snakemake.input.checkpoint,
            snakemake.input.calibration[0] if snakemake.input.calibration else None,
            config_hash=snakemake.wildcards.cell,  # the DAG's hash of the config, which names the folder
            journal=journal,
            against_records=snakemake.input.against[0] if snakemake.input.against else None,
            **snakemake.params.execution,
        )
except KeyboardInterrupt as stop:
    raise SystemExit(report_stop(stop, cell, out, journal))
