"""Rule vla_params_table: paper tab:vla_params from the models' layer index (the meta-device architectures)."""

from pathlib import Path

from vlaquantbench.tables.vla_params import write_vla_params

sm = snakemake  # noqa: F821 (injected by Snakemake)
write_vla_params(sm.output.tex, sm.output.html)
Path(sm.log[0]).write_text(f"{sm.output.tex}: counted on the models' layer index\n")
