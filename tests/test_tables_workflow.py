"""Real Snakemake runs: tables follow the records, and a frozen manifest stops the DAG first."""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_tables_paper import latex_rows, paper_rows
from test_tables_summary_driven import WORKFLOW

from vlaquantbench.records import find_cells, read_cell, write_cell
from vlaquantbench.tables import load_table, render_latex, summarize
from vlaquantbench.tables.latex import read_cells
from vlaquantbench.workflow import BUILT_MANIFEST
from paths import ROOT, RECORDS, REFERENCE

TABLES = ("lattice", "oft_protect_fc2", "clustered", "calibrated_subsets")
SEED_RECORDS = REFERENCE / "seed-records"  # the authors' run-seed 1 and 2 repeats of the pi0.5 Object baseline
FLIPPED = "libero/libero_spatial/pi05/ablate-W4A4-ah-onlyadarms"  # 187/200 successes; flipping one failure gives 188

pytestmark = pytest.mark.slow


def layout(tmp_path: Path, records: Path) -> Path:
    """A workdir whose `../shared/reference` is the reference data with `records` as its records folder."""
    workdir = tmp_path / "checkout"
    workdir.mkdir()
    (workdir / "manifests").symlink_to(ROOT / "manifests")
    reference = tmp_path / "shared" / "reference"
    reference.mkdir(parents=True)
    for entry in REFERENCE.iterdir():  # the summary and the authors' other files as they are
        if entry.name != "records":
            (reference / entry.name).symlink_to(entry)
    (reference / "records").symlink_to(records)
    return workdir


def snakemake(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "snakemake", *args, "--cores", "2", "--snakefile", str(ROOT / "Snakefile"),
               "--directory", str(workdir), "--configfile", str(ROOT / "config" / "reference.yaml")]  # fmt: skip
    return subprocess.run(command, capture_output=True, text=True, timeout=600)


def records_copy(tmp_path: Path) -> Path:
    """A writable copy of the reference records (they are read-only in place)."""
    copy = tmp_path / "records-copy"
    shutil.copytree(RECORDS, copy)
    for path in copy.rglob("*"):
        path.chmod(0o755 if path.is_dir() else 0o644)
    return copy


def flipped_copy(tmp_path: Path) -> Path:
    copy = records_copy(tmp_path)
    record = copy / f"{FLIPPED}.jsonl"
    record.write_text(record.read_text().replace('"success": false', '"success": true', 1))
    return copy


def test_reference_config_builds_the_paper_tables(tmp_path):
    workdir = layout(tmp_path, RECORDS)
    definitions = tmp_path / "tables"  # the paper's table definitions, as a user editing them would have them
    shutil.copytree(ROOT / "config" / "tables", definitions)
    targets = ("tables/lattice.tex", "tables/summary.csv", "figures/scope_recovery.pdf")
    run = snakemake(workdir, *targets, "--config", f"tables_dir={definitions}")
    assert run.returncode == 0, run.stderr[-3000:]
    lattice = workdir / "tables" / "lattice.tex"
    assert latex_rows(lattice.read_text()) == paper_rows("tab:lattice")
    assert (workdir / "figures" / "scope_recovery.pdf").read_bytes().startswith(b"%PDF")
    summary = (workdir / "tables" / "summary.csv").read_bytes().split(b"\r\n")
    assert len(summary) == 65 + 2  # header, 65 cells, trailing newline

    # An edited definition re-renders its table, and only that job runs again.
    definition = definitions / "lattice.yaml"
    definition.write_text(definition.read_text().replace("caption: '", "caption: 'Edited. ", 1))
    built = {path: path.stat().st_mtime_ns for path in (workdir / "tables" / "summary.csv", workdir / targets[2])}
    again = snakemake(workdir, *targets, "--config", f"tables_dir={definitions}")
    assert again.returncode == 0, again.stderr[-3000:]
    assert "Edited." in lattice.read_text()
    assert {path: path.stat().st_mtime_ns for path in built} == built


def test_flipped_episode_changes_exactly_the_affected_numbers(tmp_path):
    records = flipped_copy(tmp_path)
    workdir = layout(tmp_path, records)
    targets = [f"tables/{name}.tex" for name in TABLES] + ["tables/summary.csv", BUILT_MANIFEST]
    run = snakemake(workdir, *targets, "--config", f"records_dir={records}", "manifest=")
    assert run.returncode == 0, run.stderr[-3000:]

    original = {ref: read_cell(path) for ref, path in find_cells(RECORDS).items()}
    for name in TABLES:
        definition = load_table(ROOT / "config" / "tables" / f"{name}.yaml")
        measured = read_cells(list(WORKFLOW.table_sources(name)), WORKFLOW.table_sources(name))  # replay columns
        before = latex_rows(render_latex(definition, {**original, **measured}))
        after = latex_rows((workdir / "tables" / f"{name}.tex").read_text())
        changed = {b[0] for b, a in zip(before, after) if a != b}
        affected = {row["label"] for row in definition.rows if FLIPPED in row.values()}
        assert len(after) == len(before) and changed == affected, name
    lattice = dict((row[0], row) for row in latex_rows((workdir / "tables" / "lattice.tex").read_text()))
    assert lattice["adaRMS"][2:] == ["94.0 [90,97]", "-5.0"]

    before_summary = summarize(original).astype(str)
    after_summary = (workdir / "tables" / "summary.csv").read_text().splitlines()[1:]
    changed = [row.split(",")[3] for row, (_, old) in zip(after_summary, before_summary.iterrows())
               if row.split(",")[:12] != old.tolist()[:12]]  # fmt: skip
    assert changed == [FLIPPED.rsplit("/", 1)[1]]
    built = (workdir / BUILT_MANIFEST).read_text().splitlines()
    frozen = (ROOT / "manifests" / "reference.tsv").read_text().splitlines()
    assert [line.split("\t")[:3] for line in built if line not in frozen] == [[f"{FLIPPED}.jsonl", "200", "188"]]


def test_published_seed_repeats_render_beside_their_seed_0_cell(tmp_path):
    """records_dir at the authors' run-seed 1 and 2 records of the pi0.5 Object baseline, read in place: tab:lattice_object
    prints them from their episodes beside seed 0 and the other cells from the summary, as the paper does."""
    workdir = layout(tmp_path, RECORDS)
    run = snakemake(workdir, "tables/lattice_object.tex", "tables/summary.csv", "--config", f"records_dir={SEED_RECORDS}", "manifest=")
    assert run.returncode == 0, run.stderr[-3000:]
    tex = (workdir / "tables" / "lattice_object.tex").read_text()
    assert latex_rows(tex) == paper_rows("tab:lattice_object")
    assert dict((row[0], row) for row in latex_rows(tex))["full precision"][2:] == ["99.0", "98.5", "99.5"]
    from_summary = re.search(r"(\d+) of (\d+) cells \(([^)]*)\) come from the authors' per-cell summary", " ".join(tex.split()))
    summarized = from_summary[3].replace("\\_", "_").split(", ")
    assert int(from_summary[2]) - int(from_summary[1]) == 2 and "libero_object/pi05/rtn-BASELINE-e2e" in summarized
    assert not {f"libero_object/pi05/seed{run_seed}-rtn-BASELINE-e2e" for run_seed in (1, 2)} & set(summarized)
    # the summary this project writes from the records holds the authors' rows of both cells
    ours = (workdir / "tables" / "summary.csv").read_bytes().split(b"\r\n")
    authors = (REFERENCE / "authors-summary.csv").read_bytes().split(b"\r\n")
    repeats = [line for line in authors if b"libero,libero_object,pi05,seed1-rtn-BASELINE-e2e," in line
               or b"libero,libero_object,pi05,seed2-rtn-BASELINE-e2e," in line]  # fmt: skip
    assert len(repeats) == 2 and ours[1:-1] == repeats


def test_frozen_manifest_refuses_every_table(tmp_path):
    records = flipped_copy(tmp_path)
    workdir = layout(tmp_path, records)
    targets = [f"tables/{name}.tex" for name in TABLES] + ["tables/summary.csv", "figures/scope_recovery.pdf"]
    run = snakemake(workdir, *targets)
    assert run.returncode != 0
    assert f"records/{FLIPPED}.jsonl does not match manifest" in run.stderr
    # Each rendering job checks its own records first: a job fed by the changed record leaves no output. A
    # table whose records all match the manifest may still render, depending on the order Snakemake runs jobs in.
    fed = [name for name in TABLES if FLIPPED in (ROOT / "config" / "tables" / f"{name}.yaml").read_text()]
    assert fed  # the flipped record reaches some table, or this test would check nothing
    refused = {f"tables/{name}.{ext}" for name in fed for ext in ("tex", "html")} | {"tables/summary.csv"}
    written = {p.relative_to(workdir).as_posix() for folder in ("tables", "figures") for p in (workdir / folder).glob("*")}
    assert not written & refused


def test_a_corrupt_cell_folder_is_refused_by_name_and_its_old_table_removed(tmp_path):
    """Without a frozen manifest the table's own job reads the record: it fails naming the file, and the table
    an earlier run wrote is gone (Snakemake removes a job's old outputs when it runs the job)."""
    records = records_copy(tmp_path)
    ref = "libero/libero_spatial/pi05/rtn-W4A4-ah"  # in tab:lattice, as this project's cell folder
    cell = read_cell(records / f"{ref}.jsonl")
    write_cell(records / ref, cell.header, cell.episodes)
    (records / f"{ref}.jsonl").unlink()
    workdir = layout(tmp_path, records)
    built = snakemake(workdir, "tables/lattice.tex", "--config", f"records_dir={records}", "manifest=")
    assert built.returncode == 0, built.stderr[-3000:]
    assert latex_rows((workdir / "tables" / "lattice.tex").read_text()) == paper_rows("tab:lattice")

    episodes = records / ref / "episodes.parquet"
    episodes.write_bytes(episodes.read_bytes()[:500])
    refused = snakemake(workdir, "tables/lattice.tex", "--config", f"records_dir={records}", "manifest=")
    assert refused.returncode != 0
    assert f"paper_table failed: {episodes}: not a readable parquet file" in refused.stderr
    assert not (workdir / "tables" / "lattice.tex").exists() and not (workdir / "tables" / "lattice.html").exists()
