"""Rule summary: tables/summary.csv, one row per cell with the authors' columns."""

from vlaquantbench.tables import write_summary

write_summary(dict(zip(snakemake.params.refs, snakemake.input.cells)), snakemake.output[0])  # noqa: F821
