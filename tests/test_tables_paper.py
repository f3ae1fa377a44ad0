"""Tables: every number of the regenerated paper tables equals the paper's printed value."""

import re
from dataclasses import replace

import pytest
import yaml

from vlaquantbench.errors import UserError
from vlaquantbench.records import find_cells, read_cell
from vlaquantbench.tables import load_table, render_latex, write_summary
from paths import ROOT, REFERENCE, PAPER_TEX as PAPER

TABLES = ("lattice", "oft_protect_fc2", "clustered", "calibrated_subsets")
BOOTSTRAP_TOLERANCE_PP = 1.5


def latex_rows(block: str) -> list[list[str]]:
    """Data rows of a booktabs tabular (after the header's midrule) or a longtable (after its endfoot)."""
    if r"\endfoot" in block:
        body = block.split(r"\endfoot", 1)[1].split(r"\end{longtable}")[0]
    else:
        body = block.split(r"\midrule", 1)[1].split(r"\bottomrule")[0]
    rows = []
    for line in body.split("\\\\"):
        line = line.replace(r"\midrule", "").strip()
        if "&" in line:
            rows.append([" ".join(cell.split()) for cell in line.split("&")])
    return rows


def paper_rows(label: str) -> list[list[str]]:
    tex = PAPER.read_text()
    at = tex.index(rf"\label{{{label}}}")
    if r"\begin{longtable}" in tex[tex.rindex(r"\begin{", 0, at) - 200 : at]:
        block = tex[at : tex.index(r"\end{longtable}", at) + len(r"\end{longtable}")]
    else:
        start = tex.rindex(r"\begin{tabular}", 0, at)
        block = tex[start : tex.index(r"\end{tabular}", start)]
    return latex_rows(block)


def interval(text: str) -> tuple[float, float]:
    low, high = re.fullmatch(r"\[([-+]\d+\.\d), ([-+]\d+\.\d)\]", text).groups()
    return float(low), float(high)


@pytest.fixture(scope="module")
def cells():
    return {ref: read_cell(path) for ref, path in find_cells(REFERENCE / "records").items()}


def rendered_rows(name, cells):
    return latex_rows(render_latex(load_table(ROOT / "config" / "tables" / f"{name}.yaml"), cells))


@pytest.mark.parametrize("name", ["lattice", "oft_protect_fc2"])  # every other table: test_tables_summary_driven
def test_table_equals_the_paper(name, cells):
    ours, paper = rendered_rows(name, cells), paper_rows(f"tab:{name}")
    assert len(paper) == {"lattice": 14, "oft_protect_fc2": 4}[name]
    assert ours == paper


def test_clustered_equals_the_paper(cells):
    """One default_rng(0) stream shared by the 30 contrasts in row order gives all 60 endpoints exactly."""
    ours, paper = rendered_rows("clustered", cells), paper_rows("tab:clustered")
    assert len(paper) == len(ours) == 30
    assert ours == paper


def test_clustered_with_independent_streams_stays_within_tolerance(cells):
    """The floor: each contrast on its own default_rng(0) lands within 1.5 pp of every printed endpoint."""
    definition = load_table(ROOT / "config" / "tables" / "clustered.yaml")
    independent = replace(definition, bootstrap=replace(definition.bootstrap, stream="per_contrast"))
    ours, paper = latex_rows(render_latex(independent, cells)), paper_rows("tab:clustered")
    assert ours != paper  # the stream is what makes the rows exact
    for mine, printed in zip(ours, paper):
        assert mine[:4] == printed[:4]  # label, A, B, delta
        for got, want in zip(interval(mine[4]), interval(printed[4])):
            assert abs(got - want) <= BOOTSTRAP_TOLERANCE_PP, (printed[0], mine[4], printed[4])


def test_summary_equals_the_authors_rows(tmp_path):
    out = write_summary(find_cells(REFERENCE / "records"), tmp_path / "summary.csv")
    ours = out.read_bytes().split(b"\r\n")
    authors = (REFERENCE / "authors-summary.csv").read_bytes().split(b"\r\n")
    assert ours[0] == authors[0] and ours[-1] == b""
    keys = {b",".join(line.split(b",")[:4]) for line in ours[1:-1]}
    assert len(keys) == 65
    assert ours[1:-1] == [line for line in authors[1:] if b",".join(line.split(b",")[:4]) in keys]


def test_unmeasured_entries_print_a_dash(cells):
    definition = load_table(ROOT / "config" / "tables" / "calibrated_subsets.yaml")
    assert [row[3] for row in latex_rows(render_latex(definition, cells))].count("--") == 3


GOOD_TABLE = {"caption": "c", "align": "lr", "header": [["a", "b"]], "values": [{"stat": "rate", "cell": "a"}],
              "rows": [{"label": "x", "a": "libero/libero_spatial/pi05/rtn-W4A4-ah"}]}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"values": None}, "'values' is a required property"),
        ({"values": [{"stat": "median", "cell": "a"}]}, r"values.0.stat: 'median' is not allowed; allowed values: rate, rate_ci, layers"),
        ({"values": [{"stat": "delta", "cell": "a"}]}, r"values.0 \(delta\) needs minus"),
        ({"rows": [{"label": "x"}]}, "rows.0 \\(x\\) names no cell 'a'"),
        ({"rows": [{"label": "x", "a": "rtn-W4A4-ah"}]}, "rows.0.a: 'rtn-W4A4-ah' does not match"),
        ({"captoin": "c"}, "unknown key 'captoin'; allowed keys: align, bootstrap, caption, cells, environment, header"),
        ({"rows": [{"label": "x", "a": "libero/libero_spatial/pi05/rtn-W4A4-ah", "override": {"params": {"bold": True}}}]},
         r"rows.0 \(x\) overrides no column of stat params"),
        ({"rows": [{"section": "baseline {rate}"}]}, r"rows.0: the section prints \{rate\} but names no cell"),
    ],
)
def test_bad_table_definitions_are_named(tmp_path, change, message):
    raw = {k: v for k, v in {**GOOD_TABLE, **change}.items() if v is not None}
    path = tmp_path / "broken.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(UserError, match=f"{path}: .*{message}"):
        load_table(path)


def test_table_refs_are_the_rows_cells():
    refs = load_table(ROOT / "config" / "tables" / "lattice.yaml").refs()
    assert len(refs) == 15 and "libero/libero_spatial/pi05/rtn-BASELINE-e2e" in refs


def test_demo_cells_are_flagged_in_the_caption(cells):
    definition = load_table(ROOT / "config" / "tables" / "lattice.yaml")
    assert "Demo policy" not in render_latex(definition, cells)
    demo = dict(cells)
    ref = definition.rows[0]["cell"]
    demo[ref] = replace(cells[ref], header={**cells[ref].header, "variant": "demo"})
    assert r"\caption{\textbf{Demo policy with random weights" in render_latex(definition, demo)


def test_step_limits_in_a_caption_come_from_the_headers(cells):
    definition = replace(load_table(ROOT / "config" / "tables" / "lattice.yaml"), caption="Demo ({episodes}, {steps}).")
    assert "(200 episodes per cell, step limits not recorded)." in render_latex(definition, cells)  # the authors' records
    limited = {ref: replace(cell, header={**cell.header, "max_steps": 30}) for ref, cell in cells.items()}
    ref = definition.rows[0]["cell"]
    limited[ref] = replace(cells[ref], header={**cells[ref].header, "max_steps": 20})
    short = ref.split("/", 2)[-1].replace("_", "\\_")
    assert f"(200 episodes per cell, at most 30 steps per episode, 20 for {short})." in render_latex(definition, limited)


def test_the_device_in_a_caption_comes_from_the_headers(cells):
    """{device}: the GPU-trained policy's real-kernel table names the card its committed records ran on."""
    kernels = load_table(ROOT / "config" / "gpu_kernels" / "tables" / "gpu_kernels.yaml")
    recorded = {ref: read_cell(path) for ref, path in find_cells(ROOT / "results" / "gpu_study" / "fixed").items()}
    assert "in every cell; one NVIDIA H100 80GB HBM3). Success" in render_latex(kernels, recorded)
    definition = replace(load_table(ROOT / "config" / "tables" / "lattice.yaml"), caption="Demo ({device}).")
    assert "(no recorded device)." in render_latex(definition, cells)  # the authors' records name none
    placed = {ref: replace(cell, header={**cell.header, "device": {"name": "NVIDIA H200"}}) for ref, cell in cells.items()}
    ref = definition.rows[0]["cell"]
    placed[ref] = replace(cells[ref], header={**cells[ref].header, "device": {"name": "NVIDIA H100 80GB HBM3"}})
    short = ref.split("/", 2)[-1].replace("_", "\\_")
    assert f"(NVIDIA H200 for the other cells, NVIDIA H100 80GB HBM3 for {short})." in render_latex(definition, placed)


def test_a_table_mixing_quantization_semantics_versions_says_so(cells, caplog):
    definition = load_table(ROOT / "config" / "tables" / "lattice.yaml")
    assert "quantization-semantics" not in render_latex(definition, cells)  # the authors' cells: one (no) version
    mixed = dict(cells)
    ref = definition.rows[0]["cell"]
    mixed[ref] = replace(cells[ref], header={**cells[ref].header, "quant_semantics": 2})
    text = render_latex(definition, mixed)
    assert "different quantization-semantics versions (unversioned, version 2)" in text
    assert "table mixes cells of quantization-semantics unversioned, version 2" in caplog.text
