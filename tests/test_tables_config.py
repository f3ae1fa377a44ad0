"""Where the analysis rules find a cell's records, and which cells they read (WorkflowConfig)."""

import shutil

import pytest

from vlaquantbench.errors import UserError
from vlaquantbench.records import read_cell, write_cell
from vlaquantbench.workflow import WorkflowConfig
from paths import ROOT, RECORDS, REFERENCE

REF = "libero/libero_spatial/pi05/rtn-W4A4-ah"


def config(records_dir, tables=("lattice",)):
    return WorkflowConfig.from_snakemake({"records_dir": str(records_dir), "tables": list(tables)}, ROOT)


def test_records_mode_reads_authors_jsonl_and_cell_folders(tmp_path):
    shutil.copy(RECORDS / f"{REF}.jsonl", tmp_path / "a.jsonl")
    cell = read_cell(tmp_path / "a.jsonl")
    write_cell(tmp_path / "libero" / "libero_spatial" / "pi05" / "rtn-W4A4-ah", cell.header, cell.episodes)
    wf = config(tmp_path, tables=())
    assert wf.cell_input(REF) == str(tmp_path / REF / "episodes.parquet")
    assert config(RECORDS).cell_input(REF) == str(RECORDS / f"{REF}.jsonl")


def test_unknown_cell_is_named(tmp_path):
    with pytest.raises(UserError, match=r"cell libero/x/pi05/y is not in records_dir .*neither libero/x/pi05/y.jsonl"):
        config(RECORDS).cell_input("libero/x/pi05/y")


def test_cell_refs_cover_every_recorded_cell_and_every_table():
    wf = config(RECORDS, tables=("lattice", "replay_bias"))  # tables without a definition are other rules'
    assert len(wf.cell_refs()) == 65
    assert set(wf.table("lattice").refs()) <= set(wf.cell_refs())
    figure = wf.figure("scope_recovery").refs()
    with pytest.raises(UserError, match="figures/s.pdf: cell libero/libero_spatial/pi05/seed1-.* no success_summary is set"):
        wf.record_refs(figure, "figures/s.pdf")  # its seed repeats have no records here
    summarized = WorkflowConfig.from_snakemake({**wf.raw, "success_summary": str(REFERENCE / "authors-summary.csv")}, ROOT)
    assert set(summarized.record_refs(figure, "f")) <= set(wf.table("lattice").refs())
    assert summarized.summary_input(figure, "f") == [str(REFERENCE / "authors-summary.csv")]
    assert {"lattice", "clustered", "oft_protect_fc2", "calibrated_subsets"} <= set(wf.table_names())


def test_measurement_files_are_named_by_source(tmp_path):
    wf = WorkflowConfig.from_snakemake({"sources": {"latency": str(REFERENCE / "authors-files/results/latency")}}, ROOT)
    found = wf.table_sources("efficiency")
    assert found["latency:openvla_oft/baseline.jsonl"] == str(REFERENCE / "authors-files/results/latency/openvla_oft/baseline.jsonl")
    with pytest.raises(UserError, match="tables/fidelity.tex: cell fidelity:openvla_oft/awq-W3-llm.json names source 'fidelity'"):
        wf.table_sources("fidelity")


def test_dag_mode_tables_read_only_checked_cells():
    wf = WorkflowConfig.from_snakemake({"tables": ["oft_protect_fc2"], "study": {}}, ROOT)
    lattice = wf.table("lattice").refs()
    with pytest.raises(UserError, match=rf"tables/lattice.tex reads cell {lattice[0]}, which the manifest check"):
        wf.checked_refs(lattice, "tables/lattice.tex")
    assert wf.checked_refs(wf.table("oft_protect_fc2").refs(), "x") == wf.table("oft_protect_fc2").refs()
