"""Rule vla_params_table: paper tab:vla_params from the models' layer index (the meta-device architectures)."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.rule_log import job_log
from vlaquantbench.tables.vla_params import write_vla_params

sm = snakemake
with job_log(sm):
    write_vla_params(sm.input.definition, sm.output.tex, sm.output.html)
    print(f"{sm.output.tex}: counted on the models' layer index")
