"""Rule proxy_audit_table: tables/proxy_audit.tex (+ per-scope CSV and browser page) from the layer diagnostics."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.diagnostics.proxy_audit import write_proxy_audit
from vlaquantbench.rule_log import job_log

sm = snakemake
with job_log(sm):
    write_proxy_audit(dict(zip(sm.params.models, sm.input.diagnostics)), sm.input.success, sm.output.table,
                      scopes_output=sm.output.scopes, cohort=sm.params.cohort, html_output=sm.output.html)
    print(f"{sm.output.table} from {sm.params.source}")
