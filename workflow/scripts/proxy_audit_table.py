from vlaquantbench.diagnostics.proxy_audit import write_proxy_audit

write_proxy_audit(snakemake.params.diagnostics_dir, snakemake.input.success, snakemake.output.table)
