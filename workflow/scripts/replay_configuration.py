"""Rule replay_configuration: one configuration replayed on the recorded trajectories."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.replay.configuration import replay_to
from vlaquantbench.rule_log import job_log

with job_log(snakemake):
    replay_to(snakemake.input.records, snakemake.input.trajectories, snakemake.params.study,
              snakemake.wildcards.config, snakemake.params.preset, snakemake.output.summary, snakemake.output.arrays,
              snakemake.params.checkpoint_dir)
