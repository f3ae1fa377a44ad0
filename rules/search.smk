# Precision search (issue 52): the cheapest cell of a table's space decided not worse than its baseline.
# `search` in the config: the table, the baseline, alpha (over the whole search) and margin_pp; the chosen
# allocation by name (search.allocation) in tables/search_chosen.yaml, a config that a later run adds.


rule search_table:
    input:
        manifest=FROZEN_MANIFEST,
        cells=lambda wc: records_of(search_cells()[1]),
        headers=lambda wc: headers_of(search_cells()[1]),
        held_out=lambda wc: list(search_held_out().values()),
        held_out_headers=lambda wc: [str(Path(path).with_name(HEADER_FILE)) for path in search_held_out().values()],
        held_out_manifest=CONFIRM_MANIFEST,
    output:
        csv=SEARCH_TARGET,
        figure=report("figures/search_pareto.pdf", caption="../workflow/report/search.rst", category="Figures"),
        chosen=SEARCH_CHOSEN,
    log:
        "logs/tables/search.log",
    params:
        records_root=str(WF.records_root),
        baseline=lambda wc: search_cells()[0],
        refs=lambda wc: search_cells()[1],
        space=lambda wc: search_cells()[2],
        held_out_refs=lambda wc: list(search_held_out()),
        confirm_seed=SEARCH_CONFIRM.get("seed"),
        held_out_root=SEARCH_CONFIRM.get("records_dir"),
        alpha=SEARCH.get("alpha", 0.05),
        margin_pp=SEARCH.get("margin_pp", 5.0),
        allocation=SEARCH.get("allocation", "search"),
        report=lambda wc: report_params(SEARCH_TARGET),
    script:
        "../workflow/scripts/search_table.py"
