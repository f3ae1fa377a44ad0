"""Rule paper_table: one table (.tex and its browser page) from its definition, its cells' records and the summary."""

from pathlib import Path

from vlaquantbench.tables import write_table

sm = snakemake  # noqa: F821 (injected by Snakemake)
summary = sm.input.summary[0] if sm.input.summary else None
files = [*sm.input.cells, *sm.input.sources]  # the records, then the measurement files, as params.refs lists them
write_table(sm.params.definition, dict(zip(sm.params.refs, files)), sm.output.tex, summary=summary,
            html_output=sm.output.html,
            notes=[f"Data source: {sm.params.report['source']}.",
                   f"Records checked against manifest {sm.params.report['manifest']}."])
Path(sm.log[0]).write_text(f"{sm.output.tex}: {len(sm.params.refs)} cells from records, the rest from {summary}\n")
