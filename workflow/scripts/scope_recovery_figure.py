"""Rule scope_recovery_figure: figures/scope_recovery.pdf from its cells' records (seed repeats from the summary)."""

from pathlib import Path

from vlaquantbench.figures import plot_scope_recovery

sm = snakemake  # noqa: F821 (injected by Snakemake)
summary = sm.input.summary[0] if sm.input.summary else None
plot_scope_recovery(sm.params.figure, dict(zip(sm.params.refs, sm.input.cells)), sm.output[0], summary=summary)
Path(sm.log[0]).write_text(f"{sm.output[0]}: {len(sm.params.refs)} cells from records, the rest from {summary}\n")
