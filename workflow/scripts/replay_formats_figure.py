"""Rule replay_formats_figure: figures/replay_formats.pdf from the replay analysis files."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.replay.figure import write_replay_figure
from vlaquantbench.rule_log import job_log

sm = snakemake
with job_log(sm):
    write_replay_figure(dict(zip(sm.params.formats, sm.input.analyses)), sm.output[0], study=sm.params.study, formats=sm.params.formats)
    print(f"{sm.output[0]} from {sm.params.source}")
