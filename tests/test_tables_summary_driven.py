"""Every table defined in config/tables prints the paper's numbers: parsed from the paper's .tex, not copied.

Cells with episode records here are read from them; the others from the authors' per-cell summary.
"""

import re

import pytest
import yaml
from test_tables_paper import latex_rows, paper_rows

from vlaquantbench.errors import UserError
from vlaquantbench.records import find_cells
from vlaquantbench.tables import load_table
from vlaquantbench.tables.booktabs import _html_row
from vlaquantbench.tables.latex import UNAVAILABLE, read_cells, render_latex
from vlaquantbench.workflow import WorkflowConfig
from paths import ROOT, RECORDS, REFERENCE

SUMMARY = REFERENCE / "authors-summary.csv"
TABLES = sorted(path.stem for path in (ROOT / "config" / "tables").glob("*.yaml"))


@pytest.fixture(scope="module")
def records():
    return find_cells(RECORDS)


# The reference config's measurement folders (latency, fidelity), resolved from the checkout.
WORKFLOW = WorkflowConfig.from_snakemake(
    {"sources": {name: str(ROOT / folder) for name, folder in yaml.safe_load((ROOT / "config" / "reference.yaml").read_text())["sources"].items()}},
    ROOT,
)  # fmt: skip


def rendered(name, records):
    definition = load_table(ROOT / "config" / "tables" / f"{name}.yaml")
    files = {ref: records[ref] for ref in definition.refs() if ref in records} | WORKFLOW.table_sources(name)
    return definition, render_latex(definition, read_cells(definition.refs(), files, SUMMARY, f"table {name}"))


@pytest.mark.parametrize("name", [name for name in TABLES if name != "clustered"])  # clustered: test_tables_paper
def test_every_table_prints_the_papers_numbers(name, records):
    definition, tex = rendered(name, records)
    ours, paper = latex_rows(tex), paper_rows(f"tab:{name}")
    assert len(ours) == len(paper) > 0
    for mine, printed in zip(ours, paper):
        if UNAVAILABLE in mine:  # printed as unavailable, with the reason in the caption
            labels = mine.index(UNAVAILABLE)
            assert mine[:labels] == printed[:labels] and set(mine[labels:]) == {UNAVAILABLE}
            continue
        assert mine == printed, name
        # the browser page (report) shows every cell the LaTeX prints: no macro it does not know swallows one
        shown = [re.sub(r"<[^>]+>", "", _html_row([cell], "td")).strip() for cell in mine]
        assert [bool(text) for text in shown] == [bool(cell) for cell in mine], (name, mine)


def test_caption_names_the_cells_taken_from_the_summary(records):
    _, tex = rendered("components", records)
    assert "7 of 16 cells (openvla\\_oft/rtn-W4A4-ve, pi0/rtn-W4A4-ve, pi05/rtn-W4A4-llm," in tex
    assert "come from the authors' per-cell summary (authors-summary.csv), not from episode records" in tex
    assert "(success \\%; 200 episodes per cell, 190 for xvla cells)" in tex  # counted, not typed


def test_a_cell_in_neither_records_nor_summary_is_named(tmp_path, records):
    definition = load_table(ROOT / "config" / "tables" / "components.yaml")
    partial = tmp_path / "summary.csv"
    lines = SUMMARY.read_text().splitlines()
    partial.write_text("\n".join(line for line in lines if "pi0,rtn-W4A4-ve," not in line) + "\n")
    with pytest.raises(UserError, match="table components: cell libero/libero_spatial/pi0/rtn-W4A4-ve is neither in the records nor in the summary"):
        read_cells(definition.refs(), {ref: records[ref] for ref in definition.refs() if ref in records}, partial, "table components")


def test_caption_counts_follow_the_data(records):
    """A cell one episode short prints its own count in the caption (and its changed rate), not the usual 200."""
    from dataclasses import replace

    definition = load_table(ROOT / "config" / "tables" / "lattice.yaml")
    cells = read_cells(definition.refs(), {ref: records[ref] for ref in definition.refs()})
    short = "libero/libero_spatial/pi05/ablate-W4A4-ah-onlyadarms"
    cells[short] = replace(cells[short], episodes=cells[short].episodes.iloc[:-1])
    tex = render_latex(definition, cells)
    assert "(200 episodes per cell, 199 for pi05/ablate-W4A4-ah-onlyadarms)" in tex
    assert dict((row[0], row) for row in latex_rows(tex))["adaRMS"][2] == "93.5 [89,96]"  # 186/199


def test_scope_recovery_draws_the_seed_repeats_from_the_summary(tmp_path, records):
    from vlaquantbench.figures import load_figure, plot_scope_recovery

    figure = load_figure(ROOT / "config" / "figures" / "scope_recovery.yaml")
    recorded = {ref: records[ref] for ref in figure.refs() if ref in records}
    with pytest.raises(UserError, match="figure scope_recovery: cell libero/libero_spatial/pi05/seed1-"):
        plot_scope_recovery(figure, recorded, tmp_path / "f.pdf")
    assert plot_scope_recovery(figure, recorded, tmp_path / "f.pdf", summary=SUMMARY).read_bytes().startswith(b"%PDF")
    assert sum(len(entry.get("repeats", [])) for entry in figure.nested) == 5  # seeds 1 (and 2) of three scopes
