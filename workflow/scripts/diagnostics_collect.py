"""Rule diagnostics_collect: per-layer diagnostics of one scope and preset on the replay recording."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.diagnostics.collect import collect
from vlaquantbench.rule_log import job_log

with job_log(snakemake):
    collect(snakemake.input.records, snakemake.input.trajectories, snakemake.wildcards.model, snakemake.wildcards.scope, snakemake.wildcards.preset,
            snakemake.output[0], checkpoint_dir=snakemake.params.checkpoint_dir)
