"""Checkpoint stamps: pinned downloads fail with one clear line naming the checkpoint; a hub that never
answers fails in bounded time."""

import json
import os
import socket
import subprocess
import sys
import threading
import time

import pytest

from vlaquantbench.errors import UserError
from vlaquantbench.runner.checkpoint import DOWNLOAD_ATTEMPTS, download_checkpoint

MISSING_REVISION = "0" * 40  # no such commit: fails the same way with or without network
PINNED = "8e174154ef5f6c60a8da12ae99c303d8963138c1"  # config/config.yaml's pi05 revision


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


def test_a_hub_that_accepts_and_never_answers_fails_in_seconds_naming_repository_and_revision(tmp_path):
    """A real TCP server on 127.0.0.1 that accepts every connection and never sends a byte, as HF_ENDPOINT:
    the download gives up after its attempts of HF_HUB_DOWNLOAD_TIMEOUT each instead of waiting forever."""
    server = socket.create_server(("127.0.0.1", 0))
    accepted = []

    def accept():
        while True:
            try:
                accepted.append(server.accept()[0])  # held open, never answered
            except OSError:
                return

    threading.Thread(target=accept, daemon=True).start()
    config = tmp_path / "full.yaml"
    config.write_text(
        "study:\n  models:\n    pi05: {variant: full, checkpoint: lerobot/pi05_libero_finetuned_v044, "
        f"revision: '{PINNED}'}}\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "HF_HUB_OFFLINE"}
    env.update(HF_ENDPOINT=f"http://127.0.0.1:{server.getsockname()[1]}", HF_HOME=str(tmp_path / "hf"),
               HF_HUB_DOWNLOAD_TIMEOUT="1", HF_HUB_ETAG_TIMEOUT="1")
    began = time.monotonic()
    try:
        result = subprocess.run(
            [sys.executable, "-m", "vlaquantbench.cli", "rollout", "libero/libero_spatial/pi05/rtn-W4A4-ah",
             "--config", str(config), "--results", str(tmp_path)],
            capture_output=True, text=True, timeout=120, env=env,
        )
    finally:
        server.close()
        for connection in accepted:
            connection.close()
    assert time.monotonic() - began < 60
    assert accepted  # the server was reached: the time went to waiting for its answer
    assert result.returncode == 2, result.stderr[-2000:]
    assert result.stderr.startswith(f"vqb rollout: error: cannot download checkpoint lerobot/pi05_libero_finetuned_v044@{PINNED}: "
                                    f"no answer within HF_HUB_DOWNLOAD_TIMEOUT=1 s from http://127.0.0.1:")
    assert f"in {DOWNLOAD_ATTEMPTS} attempts" in result.stderr and "Traceback" not in result.stderr
    assert not list(tmp_path.rglob("checkpoint.json"))  # no stamp: the workflow sees no checkpoint
