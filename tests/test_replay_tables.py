"""The replay tables and figure rendered from the authors' analysis.json files print the paper's values."""

import re
import shutil
import subprocess
import sys

import pytest

from vlaquantbench.errors import UserError
from vlaquantbench.replay.study import StudyResults, analysis_files, load_study, success_rates
from vlaquantbench.replay.tables import write_replay_table
from paths import ROOT, REFERENCE, PAPER_TEX as PAPER

PAPER_STUDY = ROOT / "config" / "replay" / "pi05_libero_spatial.yaml"  # the paper's replay study
AUTHORS_REPLAY = REFERENCE / "authors-files/results/replay/pi05_spatial"
AUTHORS_SUMMARY = REFERENCE / "authors-summary.csv"
AUTHORS_ANALYSES = analysis_files(AUTHORS_REPLAY, load_study(PAPER_STUDY)["formats"])


def table_rows(tex: str, label: str) -> list[str]:
    """Body rows (between \\midrule and \\bottomrule) of the table carrying `label`, whitespace-normalized."""
    end = tex.index(rf"\label{{{label}}}")
    start = tex.rindex(r"\begin{table}", 0, end)
    body = tex[start:end]
    body = body[body.index(r"\midrule") + len(r"\midrule"): body.index(r"\bottomrule")]
    return [re.sub(r"\s+", " ", line).strip() for line in body.strip().splitlines() if line.strip()]


@pytest.fixture(scope="module")
def paper() -> str:
    return PAPER.read_text()


@pytest.mark.parametrize(
    "table,label,summary",
    [
        ("composition", "tab:replay_composition", None),
        ("all_formats", "tab:replay_allformats", AUTHORS_SUMMARY),
        ("bias", "tab:replay_bias", None),
    ],
)
def test_rendered_rows_equal_the_paper(tmp_path, paper, table, label, summary):
    text = write_replay_table(table, AUTHORS_ANALYSES, tmp_path / "t.tex", study=PAPER_STUDY, success_summary=summary)
    assert table_rows(text, label) == table_rows(paper, label)


def test_composition_headline_values(tmp_path):
    rows = table_rows(write_replay_table("composition", AUTHORS_ANALYSES, tmp_path / "t.tex", study=PAPER_STUDY), "tab:replay_composition")
    assert rows[-1] == r"W4A4 & 2.90 & 0.82 & 0.73 & 0.514 / 0.390 & 99.1 \\"


def test_success_column_without_records_prints_dashes(tmp_path):
    text = write_replay_table("all_formats", AUTHORS_ANALYSES, tmp_path / "t.tex", study=PAPER_STUDY, success_summary=None)
    first = table_rows(text, "tab:replay_allformats")[0]
    assert first == r"W4A4 & Attention & 72 & -- & 0.0118 & 0.066 & 0.019 \\"


def test_success_rates_come_from_successes_over_episodes():
    rates = success_rates(AUTHORS_SUMMARY)
    assert rates["libero/libero_spatial/pi05/ablate-W4A4-ah-attn_adarms"] == pytest.approx(1.5)
    assert rates["libero/libero_spatial/pi05/rtn-W4-ah"] == pytest.approx(97.5)


def test_bad_inputs_name_the_file(tmp_path):
    with pytest.raises(UserError, match=r"W4A8/analysis.json"):
        StudyResults.from_files(analysis_files(tmp_path, load_study(PAPER_STUDY)["formats"]), load_study(PAPER_STUDY))
    partial = tmp_path / "partial"
    for fmt in ("W4", "W4A8", "W4A4"):
        shutil.copytree(AUTHORS_REPLAY / fmt, partial / fmt)
    study = load_study(PAPER_STUDY)
    study["configurations"]["extra"] = {"cell": "x", "layers": 1, "label": "x", "bias_label": "x"}
    with pytest.raises(UserError, match=r"analysis.json has no configurations \['extra'\]"):
        StudyResults.from_files(analysis_files(partial, study["formats"]), study)
    with pytest.raises(UserError, match="no-such.csv"):
        success_rates(tmp_path / "no-such.csv")
    with pytest.raises(UserError, match="unknown replay study 'nope'"):
        load_study("nope")


@pytest.mark.slow
def test_snakemake_renders_replay_targets_from_reference_config(tmp_path):
    """Real Snakemake run of the replay table/figure rules on the reference config."""
    for item in ("Snakefile", "rules", "workflow", "config", "src", "manifests"):
        if (ROOT / item).exists():
            (tmp_path / item).symlink_to(ROOT / item)
    targets = ["tables/replay_composition.tex", "tables/replay_all_formats.tex", "tables/replay_bias.tex",
               "figures/replay_formats.pdf"]
    cmd = [sys.executable, "-m", "snakemake", *targets, "--cores", "2", "--configfile", "config/reference.yaml",
           "--config", f"replay_analysis_dir={AUTHORS_REPLAY}", f"success_summary={AUTHORS_SUMMARY}"]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    paper = PAPER.read_text()
    for target, label in zip(targets, ("tab:replay_composition", "tab:replay_allformats", "tab:replay_bias")):
        assert table_rows((tmp_path / target).read_text(), label) == table_rows(paper, label)
    assert (tmp_path / targets[3]).read_bytes().startswith(b"%PDF")


@pytest.mark.slow
def test_success_column_from_the_records_in_reference_mode(tmp_path):
    """With success_summary emptied, SR comes from this project's tables/summary.csv, built from the
    authors' records: the five W4A4 cells have records, the W4/W4A8 cells do not."""
    for item in ("Snakefile", "rules", "workflow", "config", "src", "manifests"):
        if (ROOT / item).exists():
            (tmp_path / item).symlink_to(ROOT / item)
    cmd = [sys.executable, "-m", "snakemake", "tables/replay_all_formats.tex", "--cores", "2",
           "--configfile", "config/reference.yaml", "--config", f"replay_analysis_dir={AUTHORS_REPLAY}",
           f"records_dir={REFERENCE / 'records'}", "success_summary="]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = table_rows((tmp_path / "tables/replay_all_formats.tex").read_text(), "tab:replay_allformats")
    assert rows[:5] == table_rows(PAPER.read_text(), "tab:replay_allformats")[:5]
    assert rows[6] == r"W4 & Attention & 72 & -- & 0.0018 & 0.012 & 0.004 \\"
