# Sequential evaluation (issue 32): the stopping rule replayed on the recorded contrasts of other tables.
# `sequential` in the config: which tables' contrasts (default tab:clustered and tab:lattice), alpha, margin and
# the study-level option `family` (issue 47: e_bh by default, split or none).


rule sequential_table:
    input:
        manifest=FROZEN_MANIFEST,
        cells=lambda wc: records_of(sequential_refs()),
        headers=lambda wc: headers_of(sequential_refs()),
    output:
        tex=SEQUENTIAL_TARGET,
        csv="tables/sequential.csv",
        figure=report("figures/sequential_episodes.pdf", caption="../workflow/report/sequential.rst", category="Figures"),
    log:
        "logs/tables/sequential.log",
    params:
        records_root=str(WF.records_root),
        refs=lambda wc: sequential_refs(),
        definitions=lambda wc: [WF.table(name) for name in SEQUENTIAL_TABLES],
        alpha=SEQUENTIAL.get("alpha", 0.05),
        margin_pp=SEQUENTIAL.get("margin_pp", 5.0),
        family=SEQUENTIAL.get("family"),
        report=lambda wc: report_params(SEQUENTIAL_TARGET),
    script:
        "../workflow/scripts/sequential_table.py"
