"""Rule replay_formats_figure: figures/replay_formats.pdf from the replay analysis files."""

from pathlib import Path

from vlaquantbench.replay.figure import write_replay_figure

sm = snakemake  # noqa: F821 (injected by Snakemake)
write_replay_figure(sm.params.analysis_dir, sm.output[0], study=sm.params.study, formats=sm.params.formats)
Path(sm.log[0]).write_text(f"{sm.output[0]} from {sm.params.source}\n")
