"""Rule demonstrations: a benchmark's scripted-expert episodes as a LeRobotDataset, one worker per thread."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821
from pathlib import Path

from vlaquantbench.demonstrations import write_demonstrations
from vlaquantbench.rule_log import job_log

with job_log(snakemake):
    write_demonstrations(snakemake.params.config, Path(snakemake.output.summary).parent, snakemake.threads)
