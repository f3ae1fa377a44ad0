"""Rule rollout: one cell's closed-loop episodes -> header.json + episodes.parquet in the cell's folder (resumes
the cell's journal beside them, which the rule declares as a log: Snakemake keeps a failed job's logs)."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from pathlib import Path

from vlaquantbench.runner.cell import run_cell
from vlaquantbench.rule_log import job_log

with job_log(snakemake):
    run_cell(
        snakemake.params.cell,
        Path(snakemake.output.header).parent,
        snakemake.input.checkpoint,
        snakemake.input.calibration[0] if snakemake.input.calibration else None,
        journal=snakemake.params.state["journal"],
        **snakemake.params.execution,
    )
