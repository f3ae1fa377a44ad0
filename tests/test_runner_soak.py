"""CI's short soak (tests/soak_kill9.py): a seeded kill -9 of a running real-LIBERO cell after it
journaled an episode and one while it writes its records, then the resumed cell equals an uninterrupted one: nothing lost, nothing
run twice, the same records, no partial or stray record file."""

import json
import subprocess
import sys

import pytest

from paths import ROOT

pytestmark = pytest.mark.slow


def test_kill_9s_while_running_and_while_writing_lose_and_duplicate_nothing_and_resume_exactly(tmp_path):
    out = tmp_path / "soak.json"
    soak = subprocess.run(
        [sys.executable, str(ROOT / "tests" / "soak_kill9.py"), "--kills", "2", "--write-kills", "1", "--tasks", "0",
         "--episodes-per-task", "3", "--max-steps", "10", "--window", "4", "--startup-window", "8",
         "--anchor-p", "0", "0", "1", "--seed", "1", "--out", str(out)],
        timeout=1500,
    )
    result = json.loads(out.read_text())
    assert result["kills"] == 2 and result["episodes"] == 3
    assert result["kills_by_phase"]["write"] == 1
    assert result["lost_episodes"] == 0 and result["duplicated_episodes"] == 0
    assert not result["parquet_before_complete"]  # the workflow never saw a partial cell
    assert not result["parquet_unreadable_or_partial"] and result["temporary_files_left"] == []
    assert result["outcomes_and_digests_equal"] and result["records_equal_but_timing"] and result["headers_equal"]
    assert soak.returncode == 0  # the script's own verdict agrees
