"""Paper `tab:vla_params` regenerated from the models' layer index (the architectures built on the meta device;
tests/test_scopes_counts.py checks the index against the builders), compared with the paper's .tex."""

from test_tables_paper import PAPER, latex_rows, paper_rows

from paths import ROOT
from vlaquantbench.tables.vla_params import vla_params_table


def test_vla_params_prints_the_papers_rows_and_caption(tmp_path):
    table = vla_params_table(ROOT / "config" / "layer_index_tables" / "vla_params.yaml")
    out = table.write(tmp_path / "vla_params.tex", tmp_path / "vla_params.html")
    tex = out.read_text()
    assert latex_rows(tex) == paper_rows("tab:vla_params")
    caption = tex.split(r"\caption{", 1)[1].split(r"}\label", 1)[0]
    assert " ".join(caption.split()) in " ".join(PAPER.read_text().split())
    assert "tab:vla_params" in (tmp_path / "vla_params.html").read_text()
