"""Manifests: the committed reference manifest, portability, and verification errors naming the file."""

import shutil
from pathlib import Path

import pytest

from vlaquantbench.cli import main
from vlaquantbench.errors import UserError
from vlaquantbench.manifest import read_manifest, verify_manifest, write_manifest
from paths import ROOT, RECORDS

FROZEN = ROOT / "manifests" / "reference.tsv"
CELL = Path("libero/libero_spatial/pi05/ablate-W4A4-ah-onlyadarms.jsonl")


@pytest.fixture
def records_copy(tmp_path):
    copy = tmp_path / "records"
    shutil.copytree(RECORDS, copy)
    for path in copy.rglob("*"):
        path.chmod(0o755 if path.is_dir() else 0o644)
    return copy


def test_committed_manifest_is_the_reference_records(tmp_path):
    rows = read_manifest(FROZEN)
    assert len(rows) == 65 and rows[CELL.as_posix()].successes == 187
    assert write_manifest(RECORDS, tmp_path / "m.tsv").read_text() == FROZEN.read_text()
    assert len(verify_manifest(FROZEN, RECORDS)) == 65


def test_manifest_is_portable(records_copy, tmp_path):
    assert write_manifest(records_copy, tmp_path / "m.tsv").read_text() == FROZEN.read_text()


def test_changed_record_is_named(records_copy):
    path = records_copy / CELL
    path.write_text(path.read_text().replace('"success": false', '"success": true', 1))
    with pytest.raises(UserError, match=rf"record {path} does not match manifest"):
        verify_manifest(FROZEN, records_copy)


def test_missing_and_unlisted_records_are_named(records_copy, tmp_path):
    (records_copy / CELL).unlink()
    with pytest.raises(UserError, match=rf"record {records_copy / CELL} listed in manifest .* is missing"):
        verify_manifest(FROZEN, records_copy)
    shutil.copy(RECORDS / CELL, records_copy / CELL)
    extra = records_copy / "libero" / "libero_spatial" / "pi05" / "extra.jsonl"
    shutil.copy(RECORDS / CELL, extra)
    with pytest.raises(UserError, match=rf"record {extra} is not listed in manifest"):
        verify_manifest(FROZEN, records_copy)


def test_manifest_with_wrong_columns_is_named(tmp_path):
    bad = tmp_path / "bad.tsv"
    bad.write_text("path\tsha256\nx.jsonl\tabc\n")
    with pytest.raises(UserError, match=rf"manifest {bad}: expected columns path, episodes, successes, sha256"):
        verify_manifest(bad, RECORDS)


def test_cli_writes_and_checks(records_copy, tmp_path, capsys):
    out = tmp_path / "manifest.tsv"
    assert main(["manifest", str(records_copy), "-o", str(out)]) == 0
    assert out.read_text() == FROZEN.read_text()
    assert main(["manifest", str(records_copy), "--check", str(FROZEN)]) == 0
    path = records_copy / CELL
    path.write_text(path.read_text() + "\n")
    assert main(["manifest", str(records_copy), "--check", str(FROZEN)]) == 2
    assert f"record {path} does not match manifest" in capsys.readouterr().err
