"""Rule search_table: the precision search over a table's cells, its per-candidate CSV and Pareto figure."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.manifest import verified
from vlaquantbench.records import read_checked_cell
from vlaquantbench.rule_log import job_log
from vlaquantbench.search import SearchDesign
from vlaquantbench.tables.search import write_search

sm = snakemake
with job_log(sm):
    # The records (checked against the frozen manifest, if any, in this job; read through read_checked_cell).
    files = verified(sm.input.manifest, sm.params.records_root, sm.input.cells)
    cells = {ref: read_checked_cell(ref, path) for ref, path in zip(sm.params.refs, files)}
    held_files = verified(sm.input.held_out_manifest, sm.params.held_out_root, sm.input.held_out)
    held = {ref: read_checked_cell(ref, path) for ref, path in zip(sm.params.held_out_refs, held_files)}
    report = write_search(cells, sm.params.baseline, SearchDesign(sm.params.alpha, sm.params.margin_pp),
                          sm.output.csv, sm.output.figure, decide_all=True, held=held,
                          confirm_seed=sm.params.confirm_seed, chosen=sm.output.chosen,
                          allocation=sm.params.allocation, space=sm.params.space)
    print("\n".join(report.summary()))
