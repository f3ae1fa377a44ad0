"""Rule replay_bias_table: tables/replay_bias.tex and its browser page from the replay analysis files."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.replay.tables import write_replay_table
from vlaquantbench.rule_log import job_log

sm = snakemake
with job_log(sm):
    write_replay_table("bias", dict(zip(sm.params.formats, sm.input.analyses)), sm.output.tex, study=sm.params.study, formats=sm.params.formats,
                       html_output=sm.output.html)
    print(f"{sm.output.tex} from {sm.params.source}")
