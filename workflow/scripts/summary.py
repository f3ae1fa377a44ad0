"""Rule summary: tables/summary.csv, one row per cell with the authors' columns."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.manifest import verified
from vlaquantbench.rule_log import job_log
from vlaquantbench.tables import write_summary

with job_log(snakemake):
    cells = verified(snakemake.input.manifest, snakemake.params.records_root, snakemake.input.cells)
    write_summary(dict(zip(snakemake.params.refs, cells)), snakemake.output[0])
