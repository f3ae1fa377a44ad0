"""Rule sequential_table: tab:sequential, its per-contrast CSV and the episodes-saved figure from the records."""
# snakemake is injected by Snakemake's script directive.
# ruff: noqa: F821

from vlaquantbench.manifest import verified
from vlaquantbench.rule_log import job_log
from vlaquantbench.sequential import DEFAULT_FAMILY, Design, live_episodes, saved_fraction
from vlaquantbench.tables.sequential import write_sequential_table

sm = snakemake
with job_log(sm):
    # The records (checked against the frozen manifest, if any, in this job; read through read_checked_cell).
    files = verified(sm.input.manifest, sm.params.records_root, sm.input.cells)
    table = write_sequential_table(sm.params.definitions, dict(zip(sm.params.refs, files)), sm.output.tex, sm.output.csv,
                                   sm.output.figure, Design(alpha=sm.params.alpha, margin_pp=sm.params.margin_pp),
                                   notes=[f"Data source: {sm.params.report['source']}.",
                                          f"Records checked against {sm.params.report['checks']}."],
                                   family=sm.params.family or DEFAULT_FAMILY)
    print(f"{sm.output.tex}: {len(table)} contrasts, {100 * saved_fraction(table):.1f}% fewer episodes, "
          f"{int((~table['agrees']).sum())} contradicting the full-sample decision")
    # Live, batches that fill a cell's workers may run past the deciding round (README "The paper's 409 runs").
    for workers in (16, 32, 64):
        run = live_episodes(table, workers).sum()
        print(f"live with {workers} workers per cell: {run} episodes, {100 * (1 - run / table['episodes_available'].sum()):.1f}% fewer")
