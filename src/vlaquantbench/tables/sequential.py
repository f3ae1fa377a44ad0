"""tab:sequential: the stopping rule (`vlaquantbench.sequential`) replayed on the contrasts of other tables.

Its rows are the (cell, minus) pairs of the listed tables' difference columns (`TableDefinition.contrasts`),
each once, in the tables' order; it writes the LaTeX table, the per-contrast CSV and a figure of the
episodes each contrast saves.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import pandas as pd

from vlaquantbench.atomic import atomic_write
from vlaquantbench.errors import UserError
from vlaquantbench.records import contrast_mismatch, read_checked_cell
from vlaquantbench.sequential import (DEFAULT_FAMILY, Design, ran_in_full, retrospective,
                                      saved_fraction, study_guarantee, write_csv)
from vlaquantbench.tables.booktabs import Booktabs
from vlaquantbench.tables.definition import TableDefinition

DECISION_TEXT = {"worse": "worse", "not_worse": "not worse", "undecided": "--", "": "n/a"}
COLOURS = {"worse": "tab:red", "not_worse": "tab:green", "undecided": "tab:gray"}


def sequential_contrasts(definitions: list[TableDefinition]) -> list[tuple[str, str]]:
    """Every contrast of `definitions`, each once, in their order."""
    return list(dict.fromkeys(pair for definition in definitions for pair in definition.contrasts()))


def _label(ref: str) -> str:
    return ref.split("/", 1)[-1].replace("_", r"\_")  # suite/model/cell: OFT cells repeat across suites


def _interval(low: float, high: float) -> str:
    return "" if pd.isna(low) else f"[{low:+.1f}, {high:+.1f}]"


def sequential_booktabs(table: pd.DataFrame, design: Design, sources: list[str], notes: list[str] | None = None,
                        family: str = DEFAULT_FAMILY) -> Booktabs:
    rows = [[_label(row.cell), _label(row.baseline), f"{row.delta_at_stop_pp:+.1f}",
             _interval(row.anytime_cs_low_pp, row.anytime_cs_high_pp),
             _interval(row.full_sample_bootstrap_low_pp, row.full_sample_bootstrap_high_pp),
             DECISION_TEXT[row.full_sample_decision], DECISION_TEXT[row.decision], DECISION_TEXT[row.study_decision],
             f"{row.episodes_used}/{row.episodes_available}"]
            for row in table.itertuples()]
    used, available = int(table["episodes_used"].sum()), int(table["episodes_available"].sum())
    contradictions = int((~table["agrees"]).sum())
    changed = int((table["study_decision"] != table["decision"]).sum())
    caption = (
        f"Sequential evaluation of the {len(table)} contrasts of {', '.join(sources)} (A $-$ B, pp). "
        f"Episodes are taken round-robin over tasks; after each round two one-sided tests by betting decide "
        f"\\emph{{worse}} ($\\Delta<0$) or \\emph{{not worse}} ($\\Delta>-{design.margin_pp:g}$ pp) at "
        f"$\\alpha={design.alpha:g}$, anytime-valid with the suite's tasks fixed; -- is no decision at the cap "
        f"(the recorded episodes). $\\Delta$ at stop is paired over the rounds the rule read, with its anytime-valid "
        f"confidence sequence there at the rule's level (hedged capital, Waudby-Smith \\& Ramdas). "
        f"The fixed design's decision reads the task-clustered bootstrap's 95\\% interval over all recorded episodes "
        f"(5,000 draws, a fixed-sample interval) the same way. {study_guarantee(family, design, len(table))} "
        f"It changes {changed} of the per-contrast decisions and reads {int(table['study_episodes_used'].sum()):,} "
        f"episodes. The per-contrast rule uses {used:,} of "
        f"{available:,} episodes ({100 * saved_fraction(table):.1f}\\% fewer); {contradictions} contrast"
        f"{'' if contradictions == 1 else 's'} contradict the fixed design."
    )
    header = ["A", "B", r"$\Delta$ at stop", r"Anytime CS", r"Bootstrap 95\% (all)", "Fixed", "Sequential", "Study",
              "Episodes"]
    return Booktabs(align="llrlllllr", header=[header], rows=rows, caption=caption,
                    label="tab:sequential", environment="longtable", notes=notes or [])


def plot_episodes_saved(table: pd.DataFrame, output: str | Path) -> Path:
    """Horizontal bars of the episodes each contrast saved, coloured by its sequential decision."""
    # matplotlib here, not at import: the workflow imports this module while it builds the DAG.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    saved = table["episodes_available"] - table["episodes_used"]
    labels = [f"{row.cell.split('/', 1)[-1]} vs {row.baseline.rsplit('/', 1)[-1]}" for row in table.itertuples()]
    fig, ax = plt.subplots(figsize=(10, 0.22 * len(table) + 1.2))
    ax.barh(range(len(table)), saved, color=[COLOURS[d] for d in table["decision"]])
    ax.set_yticks(range(len(table)), labels, fontsize=6)
    ax.invert_yaxis()
    ax.set_xlabel("episodes saved per cell (of the recorded episodes)")
    ax.set_title(f"{100 * saved_fraction(table):.1f}% fewer episodes in total", fontsize=9)
    ax.legend(handles=[plt.Rectangle((0, 0), 1, 1, color=colour) for colour in COLOURS.values()],
              labels=list(COLOURS), fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    with atomic_write(output, "wb") as handle:
        fig.savefig(handle, format="pdf", metadata={"CreationDate": None})
    plt.close(fig)
    return Path(output)


def write_sequential_table(definitions: list[TableDefinition], cell_paths: Mapping[str, str | Path], tex: str | Path,
                           csv: str | Path, figure: str | Path, design: Design = Design(),
                           notes: list[str] | None = None, family: str = DEFAULT_FAMILY) -> pd.DataFrame:
    """Run the stopping rule on every contrast of `definitions` from the records `cell_paths` (reference -> file)
    under the study-level option `family` and write the table `tex`, the per-contrast `csv` and the
    episodes-saved `figure`."""
    contrasts = sequential_contrasts(definitions)
    missing = sorted({ref for pair in contrasts for ref in pair} - set(cell_paths))
    if missing:
        raise UserError(f"tab:sequential needs the episode records of {', '.join(missing)}; only their summary is available")
    cells = {ref: read_checked_cell(ref, cell_paths[ref]) for ref in dict.fromkeys(r for pair in contrasts for r in pair)}
    for cell, baseline in contrasts:
        mismatch = contrast_mismatch(cells[cell], cells[baseline])
        if mismatch:
            raise UserError(f"tab:sequential: contrast {cell} - {baseline}: {mismatch}; a contrast pairs only cells "
                            "of one model, benchmark and suite, on the same tasks and episode seeds")
    table = retrospective(contrasts, {ref: cell.episodes for ref, cell in cells.items()}, design, family,
                          stopped_early={ref for ref, cell in cells.items() if not ran_in_full(cell.header)})
    write_csv(table, csv)
    plot_episodes_saved(table, figure)
    sequential_booktabs(table, design, [f"tab:{d.name}" for d in definitions], notes, family).write(tex)
    return table
