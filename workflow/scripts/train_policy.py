"""Rule train_policy: a policy trained from scratch on the LeRobotDataset of demonstrations."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.rule_log import job_log
from vlaquantbench.training import TrainingConfig, train_policy

with job_log(snakemake):
    train_policy(snakemake.input.dataset, snakemake.params.dataset_repo_id, snakemake.input.manifest,
                 TrainingConfig.from_dict(snakemake.params.training, "rule train_policy's params"))
