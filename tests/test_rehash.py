"""Committed records stay the records of the cells the current code builds (`vqb rehash`, `vlaquantbench.rehash`).

A cell carries only the env settings its benchmark declares, so Meta-World cells stopped carrying LIBERO's
`settle_steps` and `control_mode` and their hashes changed once; pi0.5 then declared its client on Meta-World
(`BENCHMARK_CLIENTS`), so its Meta-World cells stopped carrying its LIBERO client, and their hashes changed again.
`vqb rehash` rewrote the committed headers and manifests: here every committed header is the cell config its study
config builds now, the rewrite reproduces each committed header byte for byte from its form before both (the two
settings back in its runner, the LIBERO client and the overrides taken against it, the hashes of that form) and
changes nothing when run again, and it refuses an edited header, a stopping rule's cell it was not given, or a
DAG cell folder (named by the hash it would change)."""

from __future__ import annotations

import json
import shutil

import pytest
import yaml

from paths import ROOT
from vlaquantbench.cells import cell_config, config_hash
from vlaquantbench.cli import main
from vlaquantbench.config import load_workflow_config
from vlaquantbench.errors import UserError
from vlaquantbench.manifest import verify_manifest
from vlaquantbench.models.client import client_conventions
from vlaquantbench.records import find_cells
from vlaquantbench.rehash import rehash

# records folder -> the config files (merged in order over config/config.yaml) of the study that recorded it, and
# its frozen manifest
COMMITTED = {
    "results/methods_2026": (["config/trained_cpu.yaml"], "manifests/methods_2026.tsv"),
    "results/trained_sequential/live": (["config/trained_sequential.yaml"], "manifests/trained_sequential_live.tsv"),
    "results/trained_sequential/fixed": (["config/trained_sequential.yaml", "config/trained_sequential_fixed.yaml"],
                                         "manifests/trained_sequential_fixed.tsv"),
    # the confirmation's seed1- cells: the sequential study's cells without its stopping rule
    "results/trained_search/confirm": (["config/trained_sequential.yaml", "config/trained_sequential_fixed.yaml"],
                                       "manifests/trained_search_confirm.tsv"),
}


def study_of(files: list[str]) -> dict:
    study = load_workflow_config(ROOT / files[0], ROOT / "config/config.yaml")["study"]
    for later in files[1:]:
        study = {**study, **(yaml.safe_load((ROOT / later).read_text()).get("study") or {})}
    return study


def headers(folder) -> dict:
    return {ref: json.loads((path.parent / "header.json").read_text()) for ref, path in find_cells(folder).items()}


@pytest.mark.parametrize("folder", sorted(COMMITTED))
def test_every_committed_header_is_the_cell_its_config_builds_now(folder):
    files, manifest = COMMITTED[folder]
    study = study_of(files)
    recorded = headers(ROOT / folder)
    assert recorded
    for ref, header in recorded.items():
        built = cell_config(ref, study)
        assert header["config"] == built and header["config_hash"] == config_hash(built), ref
    verify_manifest(ROOT / manifest, ROOT / folder)


def before(header: dict, renamed: dict[str, str]) -> dict:
    """A Meta-World header as it was recorded, before cells carried only their benchmark's env settings and before
    pi0.5 declared its client on Meta-World (its cells carried its LIBERO client, `CLIENT`)."""
    config = json.loads(json.dumps(header["config"]))
    config["runner"].update(settle_steps=10, control_mode="delta")
    config["client"] = client_conventions(config["model"]).as_dict()
    cell = {"executed_chunk": config["runner"]["executed_chunk"], "episodes_per_task": config["episodes_per_task"]}
    for key, value in cell.items():
        config["overrides"].pop(key, None)
        if value != config["client"][key]:
            config["overrides"][key] = {"cell": value, "client": config["client"][key]}
    against = config.get("sequential", {}).get("against")
    if against is not None:
        against["config_hash"] = renamed[against["config_hash"]]
    renamed[header["config_hash"]] = config_hash(config)
    return {**header, "config": config, "config_hash": config_hash(config), "client": config["client"],
            "overrides": config["overrides"]}


def test_the_rewrite_reproduces_the_committed_headers_and_manifests_and_runs_again_as_a_no_op(tmp_path, capsys):
    copies, renamed = [], {}
    for folder in COMMITTED:
        copy = tmp_path / folder
        shutil.copytree(ROOT / folder, copy)
        copies.append(copy)
    # the stopping rules' against cells first: a live cell's old config names its against cell's old hash
    for copy in sorted(copies, key=lambda c: c.name == "live"):
        for ref, path in find_cells(copy).items():
            header = json.loads((path.parent / "header.json").read_text())
            (path.parent / "header.json").write_text(json.dumps(before(header, renamed)))
    manifests = [f"--manifest={tmp_path / folder}={tmp_path / folder.replace('/', '_')}.tsv" for folder in COMMITTED]
    assert main(["rehash", *map(str, copies), *manifests]) == 0
    assert len(capsys.readouterr().out.splitlines()) == 29 + len(COMMITTED)  # every cell, then every manifest
    for folder, (_, manifest) in COMMITTED.items():
        for ref, path in find_cells(ROOT / folder).items():
            rewritten = tmp_path / folder / path.relative_to(ROOT / folder).parent / "header.json"
            assert rewritten.read_bytes() == (path.parent / "header.json").read_bytes(), ref
        assert (tmp_path / f"{folder.replace('/', '_')}.tsv").read_bytes() == (ROOT / manifest).read_bytes()
    assert rehash(copies) == []


def test_an_edited_header_or_an_against_cell_not_given_is_refused_before_anything_is_written(tmp_path):
    live = tmp_path / "live"
    shutil.copytree(ROOT / "results/trained_sequential/live", live)
    baseline = live / "metaworld/metaworld_mt50/pi05/rtn-BASELINE-e2e/header.json"
    shutil.rmtree(baseline.parent)
    with pytest.raises(UserError, match=r"rtn-W2A2-e2e/header.json: its sequential.against "
                                        r"metaworld/metaworld_mt50/pi05/rtn-BASELINE-e2e \([0-9a-f]{12}\) is not among "
                                        r"the records given .*: give its folder too"):
        rehash([live])
    shutil.copytree(ROOT / "results/trained_sequential/live/metaworld/metaworld_mt50/pi05/rtn-BASELINE-e2e", baseline.parent)
    header = json.loads(baseline.read_text())
    header["config"]["episodes_per_task"] += 1
    baseline.write_text(json.dumps(header))
    written = {path: path.read_bytes() for path in live.rglob("header.json")}
    with pytest.raises(UserError, match=r"rtn-BASELINE-e2e/header.json: config_hash [0-9a-f]{12} is not the hash of its "
                                        r"config \([0-9a-f]{12}\): the header was edited; not rewritten"):
        rehash([live])
    assert {path: path.read_bytes() for path in live.rglob("header.json")} == written
    # a DAG cell folder is named by the hash the rewrite would change
    dag = tmp_path / "cells"
    shutil.copytree(baseline.parent, dag / header["config_hash"])
    with pytest.raises(UserError, match=rf"{header['config_hash']}/header.json: its folder {header['config_hash']} is "
                                        r"not its reference metaworld/metaworld_mt50/pi05/rtn-BASELINE-e2e"):
        rehash([dag])
