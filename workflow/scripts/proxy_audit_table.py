"""Rule proxy_audit_table: tables/proxy_audit.tex (+ per-scope CSV and browser page) from the layer diagnostics."""

from pathlib import Path

from vlaquantbench.diagnostics.proxy_audit import write_proxy_audit

sm = snakemake  # noqa: F821 (injected by Snakemake)
write_proxy_audit(sm.params.diagnostics_dir, sm.input.success, sm.output.table, html_output=sm.output.html)
Path(sm.log[0]).write_text(f"{sm.output.table} from {sm.params.source}\n")
