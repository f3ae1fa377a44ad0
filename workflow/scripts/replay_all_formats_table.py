"""Rule replay_all_formats_table: tables/replay_all_formats.tex and its browser page from the replay analysis files."""

from pathlib import Path

from vlaquantbench.replay.tables import write_replay_table

sm = snakemake  # noqa: F821 (injected by Snakemake)
write_replay_table("all_formats", sm.params.analysis_dir, sm.output.tex, study=sm.params.study, success_summary=sm.input.success, formats=sm.params.formats,
                   html_output=sm.output.html)
Path(sm.log[0]).write_text(f"{sm.output.tex} from {sm.params.source}\n")
