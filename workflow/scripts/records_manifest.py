"""Rule records_manifest: a manifest of the records the tables read (when the config names none)."""

from vlaquantbench.manifest import write_manifest

write_manifest(snakemake.params.records_root, snakemake.output[0], snakemake.input.cells)  # noqa: F821
