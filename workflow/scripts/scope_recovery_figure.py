"""Rule scope_recovery_figure: figures/scope_recovery.pdf from its cells' records."""

from pathlib import Path

from vlaquantbench.figures import plot_scope_recovery

sm = snakemake  # noqa: F821 (injected by Snakemake)
plot_scope_recovery(sm.params.figure, dict(zip(sm.params.refs, sm.input.cells)), sm.output[0])
Path(sm.log[0]).write_text(f"{sm.output[0]}: {len(sm.params.refs)} cells from records\n")
