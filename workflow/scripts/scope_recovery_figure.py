"""Rule scope_recovery_figure: figures/scope_recovery.pdf from its cells' records."""

from vlaquantbench.figures import plot_scope_recovery

plot_scope_recovery(snakemake.params.figure, dict(zip(snakemake.params.refs, snakemake.input.cells)), snakemake.output[0])  # noqa: F821
