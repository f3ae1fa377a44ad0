"""Rule train_policy: a policy trained from scratch on a LeRobotDataset of demonstrations."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.rule_log import job_log
from vlaquantbench.training import train_policy

with job_log(snakemake):
    training = snakemake.params.training
    train_policy(training["dataset"], snakemake.input.manifest, training["output"], snakemake.output.provenance, training)
