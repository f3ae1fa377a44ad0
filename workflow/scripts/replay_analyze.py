"""Rule replay_analyze: one format's replay summaries -> analysis.json."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.replay.analysis import analyze_files
from vlaquantbench.rule_log import job_log

with job_log(snakemake):
    analyze_files(snakemake.input.summaries, snakemake.output[0], study=snakemake.params.study,
                  arrays=snakemake.input.arrays)
