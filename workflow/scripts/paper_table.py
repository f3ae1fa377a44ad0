"""Rule paper_table: one booktabs table from its definition and its cells' records."""

from vlaquantbench.tables import write_table

write_table(snakemake.params.definition, dict(zip(snakemake.params.refs, snakemake.input.cells)), snakemake.output[0])  # noqa: F821
