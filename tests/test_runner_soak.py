"""CI's short soak (benchmarks/soak_kill9.py): two seeded kill -9s of a running real-LIBERO cell, then
the resumed cell equals an uninterrupted one: nothing lost, nothing run twice, the same records."""

import json
import subprocess
import sys

import pytest

from paths import ROOT

pytestmark = pytest.mark.slow


def test_two_kill_9s_lose_and_duplicate_nothing_and_resume_exactly(tmp_path):
    out = tmp_path / "soak.json"
    subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "soak_kill9.py"), "--kills", "2", "--tasks", "0",
         "--episodes-per-task", "3", "--max-steps", "10", "--window", "4", "--startup-window", "8",
         "--startup-kill-p", "0.5", "--seed", "1", "--out", str(out)],
        check=True, timeout=1500,
    )
    result = json.loads(out.read_text())
    assert result["kills"] == 2 and result["episodes"] == 3
    assert result["lost_episodes"] == 0 and result["duplicated_episodes"] == 0
    assert not result["parquet_before_complete"]  # the workflow never saw a partial cell
    assert result["outcomes_and_digests_equal"] and result["records_equal_but_timing"] and result["headers_equal"]
