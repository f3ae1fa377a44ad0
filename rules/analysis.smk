# Records -> summary, tables and figures (issue: regenerate the paper's tables).
# Every job that renders records checks them itself, in the job that writes its output: the episode
# schema and the headers, and with `manifest` set, the frozen manifest file by file. A refused job fails,
# and Snakemake removes the old outputs of every job it runs: no stale table survives. Without a frozen
# manifest, `records_manifest` builds one (`paper` asks for it) but no rendering job waits for it: a record
# refused there would stop the run before the tables' jobs start, leaving their old outputs in place.


rule records_manifest:
    input:
        cells=lambda wc: records_of(WF.cell_refs()),
        headers=lambda wc: headers_of(WF.cell_refs()),
    output:
        BUILT_MANIFEST,
    params:
        records_root=str(WF.records_root),
    log:
        "logs/records_manifest.log",
    script:
        "../workflow/scripts/records_manifest.py"


rule summary:
    input:
        manifest=FROZEN_MANIFEST,
        cells=lambda wc: records_of(WF.cell_refs()),
        headers=lambda wc: headers_of(WF.cell_refs()),
    output:
        "tables/summary.csv",
    params:
        records_root=str(WF.records_root),
        refs=lambda wc: WF.cell_refs(),
    log:
        "logs/summary.log",
    script:
        "../workflow/scripts/summary.py"


rule paper_table:
    input:
        manifest=FROZEN_MANIFEST,
        cells=lambda wc: records_of(WF.checked_refs(WF.table_record_refs(wc.table), f"tables/{wc.table}.tex")),
        headers=lambda wc: headers_of(WF.checked_refs(WF.table_record_refs(wc.table), f"tables/{wc.table}.tex")),
        summary=lambda wc: WF.table_summary(wc.table),
        sources=lambda wc: list(WF.table_sources(wc.table).values()),
        definition=lambda wc: WF.table_file(wc.table),  # an edited definition re-renders its table
    output:
        tex="tables/{table}.tex",
        html=report("tables/{table}.html", caption="../workflow/report/table.rst", category="Tables",
                    labels={"table": "{table}"}),
    log:
        "logs/tables/{table}.log",
    wildcard_constraints:
        table="|".join(PAPER_TABLES),
    params:
        records_root=str(WF.records_root),
        definition=lambda wc: WF.table(wc.table),
        refs=lambda wc: WF.table_record_refs(wc.table) + list(WF.table_sources(wc.table)),
        report=lambda wc: report_params(f"tables/{wc.table}.tex"),
    script:
        "../workflow/scripts/paper_table.py"


# tab:vla_params needs no records: its counts come from the committed layer index (models/<model>/linears.json),
# written from the model builders on the meta device and compared with them by tests/test_scopes_counts.py.
rule vla_params_table:
    input:
        definition=WF.layer_index_table_file("vla_params"),  # its caption: an edited one re-renders the table
    output:
        tex="tables/vla_params.tex",
        html=report("tables/vla_params.html", caption="../workflow/report/vla_params.rst", category="Tables",
                    labels={"table": "vla_params"}),
    log:
        "logs/tables/vla_params.log",
    params:
        report={"target": "tables/vla_params.tex"},
    script:
        "../workflow/scripts/vla_params_table.py"


SCOPE_RECOVERY = "figures/scope_recovery.pdf"


rule scope_recovery_figure:
    input:
        manifest=FROZEN_MANIFEST,
        cells=lambda wc: records_of(WF.checked_refs(WF.record_refs(WF.figure("scope_recovery").refs(), SCOPE_RECOVERY), SCOPE_RECOVERY)),
        headers=lambda wc: headers_of(WF.checked_refs(WF.record_refs(WF.figure("scope_recovery").refs(), SCOPE_RECOVERY), SCOPE_RECOVERY)),
        summary=lambda wc: WF.summary_input(WF.figure("scope_recovery").refs(), SCOPE_RECOVERY),
        definition=WF.figure_file("scope_recovery"),
    output:
        report(SCOPE_RECOVERY, caption="../workflow/report/figure.rst", category="Figures"),
    log:
        "logs/figures/scope_recovery.log",
    params:
        records_root=str(WF.records_root),
        figure=lambda wc: WF.figure("scope_recovery"),
        refs=lambda wc: WF.record_refs(WF.figure("scope_recovery").refs(), SCOPE_RECOVERY),
        report=lambda wc: report_params(SCOPE_RECOVERY),
    script:
        "../workflow/scripts/scope_recovery_figure.py"


# Every table and figure the published data supports, in one target (and in `--report report.html`).
# The replay, proxy-audit and replay-figure rules live in rules/replay.smk.
rule paper:
    input:
        expand("tables/{table}.tex", table=PAPER_TABLES),
        expand("tables/{table}.tex", table=["replay_composition", "replay_all_formats", "replay_bias", "proxy_audit"]),
        "tables/vla_params.tex",
        "tables/summary.csv",
        "tables/sequential.tex",  # rules/sequential.smk: the stopping rule on tab:clustered's and tab:lattice's contrasts
        "figures/scope_recovery.pdf",
        "figures/replay_formats.pdf",
        [] if WF.manifest else BUILT_MANIFEST,
