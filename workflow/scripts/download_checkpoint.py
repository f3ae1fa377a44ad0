"""Rule download_checkpoint: the cell's checkpoint at its pinned revision (a stamp for the demo variant)."""

from vlaquantbench.runner.checkpoint import download_checkpoint

download_checkpoint(**snakemake.params.info, stamp=snakemake.output[0])  # noqa: F821
