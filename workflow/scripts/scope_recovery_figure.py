"""Rule scope_recovery_figure: figures/scope_recovery.pdf from its cells' records (cells without records, from the summary)."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.figures import plot_scope_recovery
from vlaquantbench.manifest import verified
from vlaquantbench.rule_log import job_log

sm = snakemake
with job_log(sm):
    summary = sm.input.summary[0] if sm.input.summary else None
    plot_scope_recovery(sm.params.figure, dict(zip(sm.params.refs, verified(sm.input.manifest, sm.params.records_root, sm.input.cells))), sm.output[0], summary=summary)
    print(f"{sm.output[0]}: {len(sm.params.refs)} cells from records, the rest from {summary}")
