"""Rule records_manifest: a manifest of the records the tables read (when the config names none)."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.manifest import write_manifest
from vlaquantbench.rule_log import job_log

with job_log(snakemake):
    write_manifest(snakemake.params.records_root, snakemake.output[0], snakemake.input.cells)
