"""Rule replay_record: the study's full-precision trajectories in its benchmark and their records.json."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.replay.record import record_to
from vlaquantbench.rule_log import job_log

with job_log(snakemake):
    record_to(snakemake.params.study, snakemake.params.options, snakemake.output.records, snakemake.output.trajectories)
