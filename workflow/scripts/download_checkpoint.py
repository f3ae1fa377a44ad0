"""Rule download_checkpoint: the cell's checkpoint at its pinned revision (a stamp for the demo variant)."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.runner.checkpoint import download_checkpoint
from vlaquantbench.rule_log import job_log

with job_log(snakemake):
    download_checkpoint(**snakemake.params.info, stamp=snakemake.output[0])
