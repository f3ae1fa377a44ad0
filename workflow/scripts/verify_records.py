"""Rule verify_records: stop the DAG, naming the file, if any record differs from the manifest."""

from vlaquantbench.manifest import write_verified

write_verified(snakemake.input.manifest, snakemake.params.records_root, snakemake.input.cells, snakemake.output[0])  # noqa: F821
