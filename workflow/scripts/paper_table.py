"""Rule paper_table: one table (.tex and its browser page) from its definition, its cells' records and the summary."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.manifest import verified
from vlaquantbench.rule_log import job_log
from vlaquantbench.tables import write_table

sm = snakemake
with job_log(sm):
    summary = sm.input.summary[0] if sm.input.summary else None
    # The records (checked against the frozen manifest, if any, in this job), then the measurement files, as params.refs lists them.
    files = [*verified(sm.input.manifest, sm.params.records_root, sm.input.cells), *sm.input.sources]
    write_table(sm.params.definition, dict(zip(sm.params.refs, files)), sm.output.tex, summary=summary,
                html_output=sm.output.html,
                notes=[f"Data source: {sm.params.report['source']}.",
                       f"Records checked against {sm.params.report['checks']}."])
    print(f"{sm.output.tex}: {len(sm.params.refs)} cells from records, the rest from {summary}")
