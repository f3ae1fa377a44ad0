"""Every table defined in config/tables prints the paper's numbers: parsed from the paper's .tex, not copied.

Cells with episode records here are read from them; the others from the authors' per-cell summary.
"""

import pytest
from test_tables_paper import latex_rows, paper_rows

from vlaquantbench.errors import UserError
from vlaquantbench.records import find_cells
from vlaquantbench.tables import load_table
from vlaquantbench.tables.latex import UNAVAILABLE, read_cells, render_latex
from paths import ROOT, RECORDS, REFERENCE

SUMMARY = REFERENCE / "authors-summary.csv"
TABLES = sorted(path.stem for path in (ROOT / "config" / "tables").glob("*.yaml"))
PREFIX_ONLY = {"calibrated_subsets": 4}  # its replay columns come from the replay analysis, not from cells


@pytest.fixture(scope="module")
def records():
    return find_cells(RECORDS)


def rendered(name, records):
    definition = load_table(ROOT / "config" / "tables" / f"{name}.yaml")
    cells = read_cells(definition, {ref: records[ref] for ref in definition.refs() if ref in records}, SUMMARY)
    return definition, render_latex(definition, cells)


@pytest.mark.parametrize("name", [name for name in TABLES if name != "clustered"])  # clustered: test_tables_paper
def test_every_table_prints_the_papers_numbers(name, records):
    definition, tex = rendered(name, records)
    ours, paper = latex_rows(tex), paper_rows(f"tab:{name}")
    assert len(ours) == len(paper) > 0
    for mine, printed in zip(ours, paper):
        if UNAVAILABLE in mine:  # printed as unavailable, with the reason in the caption
            assert mine[0] == printed[0] and set(mine[1:]) == {UNAVAILABLE}
            continue
        width = PREFIX_ONLY.get(name, len(printed))
        assert mine[:width] == printed[:width], name


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
        read_cells(definition, {ref: records[ref] for ref in definition.refs() if ref in records}, partial)
