"""`HF_HOME=<hub fixture> HF_HUB_OFFLINE=1 snakemake --cores 2 tables/lattice.tex --configfile
config/paper_smoke.yaml`, for real, in a copy of the workflow: the paper's checkpoints at their
pinned revisions resolve from the cache, load through lerobot (pi: `from_pretrained` and the checkpoint's
processors; X-VLA: lerobot's model and remap of the release's weights; OpenVLA-OFT: the architecture built
here, its shards and `.pt` heads loaded strictly), drive real LIBERO episodes, and
every cell header records the tokenizer and normalization it used, with their hashes."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from paths import ROOT
from vlaquantbench.hub.checks import sha256

pytestmark = pytest.mark.slow


def test_the_paper_smoke_config_runs_end_to_end_on_the_hub_fixture(hub_fixture, tmp_path):
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "config"):
        source = ROOT / item
        (shutil.copytree if source.is_dir() else shutil.copy)(source, checkout / item)
    env = {**os.environ, "HF_HOME": str(hub_fixture["home"]), "HF_HUB_OFFLINE": "1"}
    result = subprocess.run(
        # One thread per rollout: two of the five cells at a time (each mostly loads its model).
        [sys.executable, "-m", "snakemake", "--cores", "2", "tables/lattice.tex", "--configfile", "config/paper_smoke.yaml",
         "--set-threads", "rollout=1"],
        cwd=checkout, env=env, capture_output=True, text=True, timeout=1800,
    )
    assert result.returncode == 0, (result.stdout[-2000:], result.stderr[-4000:])

    table = (checkout / "tables" / "lattice.tex").read_text()
    assert "offline hub fixture" in table and "Demo policy" not in table
    assert r"$\pi_{0.5}$ W4A4, all 167 AH layers & 167 &" in table
    paligemma = hub_fixture["repos"]["google/paligemma-3b-pt-224"]
    headers = {}
    for path in (checkout / "results" / "cells").glob("*/header.json"):
        header = json.loads(path.read_text())
        headers[header["ref"]] = header
        model = hub_fixture["study"]["models"][header["model"]]
        snapshot = Path(hub_fixture["repos"][model["checkpoint"]]["path"])
        assert (header["variant"], header["checkpoint"], header["revision"]) == ("full", model["checkpoint"], model["revision"])
        if header["model"] == "xvla":  # the release's own tokenizer and image processor, in its snapshot
            tokenizer_repo, tokenizer_files = {"path": snapshot, "revision": model["revision"]}, ("tokenizer.json", "tokenizer_config.json", "vocab.json")
            assert (header["tokenizer"]["class"], header["tokenizer"]["repo"]) == ("RobertaTokenizer", model["checkpoint"])
            record = header["normalization"]["image_processor"]
            assert record["sha256"] == sha256(snapshot / "preprocessor_config.json") and record["mode"] == "bicubic"
            assert header["widths"] == "reduced (config.json)"
            assert header["chunk"] == {"predicted": 30, "executed": 10}
            assert header["environment"]["mujoco"] == "3.1.6"
        elif header["model"] == "openvla_oft":  # LLaMA-2's SentencePiece tokenizer and the suite's statistics, in its snapshot
            tokenizer_repo, tokenizer_files = {"path": snapshot, "revision": model["revision"]}, ("tokenizer.model", "tokenizer.json", "tokenizer_config.json")
            assert (header["tokenizer"]["class"], header["tokenizer"]["repo"]) == ("LlamaTokenizer", model["checkpoint"])
            record = header["normalization"]["statistics"]
            assert record["sha256"] == sha256(snapshot / "dataset_statistics.json") and record["key"] == "libero_spatial_no_noops"
            assert header["widths"] == "reduced (offline hub fixture)"
            assert header["chunk"] == {"predicted": 8, "executed": 8}
        else:
            tokenizer_repo, tokenizer_files = paligemma, ("config.json", "tokenizer.json", "tokenizer_config.json")
            assert (header["tokenizer"]["class"], header["tokenizer"]["repo"]) == ("GemmaTokenizer", "google/paligemma-3b-pt-224")
            for processor in ("policy_preprocessor", "policy_postprocessor"):
                record = header["normalization"][processor]
                assert record["sha256"] == sha256(snapshot / f"{processor}.json")
                assert record["state_files"] and all(sha256(snapshot / f) == h for f, h in record["state_files"].items())
            assert header["widths"] == "reduced (offline hub fixture)"
            assert header["chunk"] == {"predicted": 50, "executed": 10}
        assert header["tokenizer"]["revision"] == tokenizer_repo["revision"]
        assert header["tokenizer"]["files"] == {name: sha256(Path(tokenizer_repo["path"]) / name) for name in tokenizer_files}
        assert header["hooks"]["fired"] == header["hooks"]["selected"]
        assert header["episodes_per_task"] == 1 and header["max_steps"] == 30
    assert set(headers) == {"libero/libero_spatial/pi05/rtn-BASELINE-e2e", "libero/libero_spatial/pi05/rtn-W4A4-ah",
                            "libero/libero_spatial/pi0/rtn-BASELINE-e2e", "libero/libero_spatial/xvla/rtn-BASELINE-e2e",
                            "libero/libero_spatial/openvla_oft/rtn-BASELINE-e2e"}
    assert "OpenVLA-OFT unquantized &" in table
    stamp = json.loads(next((checkout / "results" / "checkpoints").glob("pi05*/checkpoint.json")).read_text())
    assert Path(stamp["path"]) == Path(hub_fixture["repos"]["lerobot/pi05_libero_finetuned_v044"]["path"])
