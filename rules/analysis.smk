# Records -> verified manifest -> summary -> tables and figures (issue: regenerate the paper's tables).
# Every table waits for `verify_records`: with `manifest` set the records must match it file by file;
# without one, a manifest is built from the records first.
PAPER_TABLES = WF.table_names()


def records_of(refs):
    """Record files of the cells `refs` (authors' .jsonl, a cell folder's episodes.parquet, or the DAG's cell)."""
    return [WF.cell_input(ref) for ref in refs]


rule records_manifest:
    input:
        cells=lambda wc: records_of(WF.cell_refs()),
    output:
        "results/records/manifest.tsv",
    params:
        records_root=str(WF.records_root),
    script:
        "../workflow/scripts/records_manifest.py"


rule verify_records:
    input:
        manifest=str(WF.manifest) if WF.manifest else rules.records_manifest.output[0],
        cells=lambda wc: records_of(WF.cell_refs()),
    output:
        "results/records/verified.tsv",
    params:
        records_root=str(WF.records_root),
    script:
        "../workflow/scripts/verify_records.py"


rule summary:
    input:
        verified=rules.verify_records.output[0],
        cells=lambda wc: records_of(WF.cell_refs()),
    output:
        "tables/summary.csv",
    params:
        refs=lambda wc: WF.cell_refs(),
    script:
        "../workflow/scripts/summary.py"


rule paper_table:
    input:
        verified=rules.verify_records.output[0],
        cells=lambda wc: records_of(WF.checked_refs(WF.table(wc.table).refs(), f"tables/{wc.table}.tex")),
    output:
        "tables/{table}.tex",
    wildcard_constraints:
        table="|".join(PAPER_TABLES),
    params:
        definition=lambda wc: WF.table(wc.table),
        refs=lambda wc: WF.table(wc.table).refs(),
    script:
        "../workflow/scripts/paper_table.py"


rule scope_recovery_figure:
    input:
        verified=rules.verify_records.output[0],
        cells=lambda wc: records_of(WF.checked_refs(WF.figure("scope_recovery").refs(), "figures/scope_recovery.pdf")),
    output:
        "figures/scope_recovery.pdf",
    params:
        figure=lambda wc: WF.figure("scope_recovery"),
        refs=lambda wc: WF.figure("scope_recovery").refs(),
    script:
        "../workflow/scripts/scope_recovery_figure.py"
