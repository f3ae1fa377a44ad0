"""Checkpoint stamps: pinned downloads fail with one clear line naming the checkpoint."""

import json
import subprocess
import sys

import pytest

from vlaquantbench.errors import UserError
from vlaquantbench.runner.checkpoint import download_checkpoint

MISSING_REVISION = "0" * 40  # no such commit: fails the same way with or without network


def test_an_unreachable_or_unknown_checkpoint_is_a_user_error_naming_it(tmp_path):
    stamp = tmp_path / "pi05-full" / "checkpoint.json"
    with pytest.raises(UserError, match=rf"cannot download checkpoint lerobot/pi05_libero_finetuned_v044@{MISSING_REVISION}"):
        download_checkpoint("pi05", "full", "lerobot/pi05_libero_finetuned_v044", MISSING_REVISION, stamp)
    assert not stamp.exists()


def test_a_full_model_needs_a_pinned_revision(tmp_path):
    with pytest.raises(UserError, match="study.models.pi05: a full-variant model needs `checkpoint` and a pinned `revision`"):
        download_checkpoint("pi05", "full", "lerobot/pi05_libero_finetuned_v044", None, tmp_path / "c.json")


def test_the_demo_variant_stamp_records_no_weights(tmp_path):
    stamp = tmp_path / "checkpoint.json"
    download_checkpoint("pi05", "demo", "lerobot/pi05_libero_finetuned_v044", None, stamp)
    assert json.loads(stamp.read_text())["path"] is None


def test_the_cli_prints_one_line_not_a_traceback(tmp_path):
    config = tmp_path / "full.yaml"
    config.write_text(
        "study:\n  models:\n    pi05: {variant: full, checkpoint: lerobot/pi05_libero_finetuned_v044, "
        f"revision: '{MISSING_REVISION}'}}\n"
    )
    result = subprocess.run(
        [sys.executable, "-m", "vlaquantbench.cli", "rollout", "libero/libero_spatial/pi05/rtn-W4A4-ah",
         "--config", str(config), "--results", str(tmp_path)],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 2
    assert result.stderr.startswith("vqb rollout: error: cannot download checkpoint lerobot/pi05_libero_finetuned_v044@")
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1
