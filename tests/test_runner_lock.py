"""One writer per cell (runner.lock): a second writer is refused naming the holder, whichever process it is;
the lock ends with its holder, a kill -9 included; a journal kept elsewhere is locked too."""

import os
import signal
import socket
import subprocess
import sys

import pytest

from vlaquantbench.runner.lock import CellLocked, lock_files, writing

REF = "libero/libero_spatial/pi05/rtn-W4A4-ah"
HOLD = ("import sys, time; from vlaquantbench.runner.lock import writing\n"
        "with writing(sys.argv[1], sys.argv[2], sys.argv[3]):\n"
        "    print('held', flush=True); time.sleep(600)")


def holder(folder, journal):
    """Another process holding the cell's lock, as a running `vqb rollout` or Snakemake job would."""
    process = subprocess.Popen([sys.executable, "-c", HOLD, str(folder), str(journal), REF], stdout=subprocess.PIPE,
                               text=True)
    assert process.stdout.readline() == "held\n"
    return process


def test_a_second_writer_is_refused_naming_the_holder_until_a_kill_9_frees_the_lock(tmp_path):
    cell = tmp_path / "cells" / "0123456789ab"
    first = holder(cell, cell / "journal.jsonl")
    try:
        with pytest.raises(CellLocked) as err:
            with writing(cell, cell / "journal.jsonl", "libero/libero_spatial/pi05/other-name"):
                pytest.fail("a second writer got the lock")
        message = str(err.value)
        assert message.startswith(f"cell libero/libero_spatial/pi05/other-name: another process writes it: "
                                  f"{cell / 'writer.lock'} is locked by pid {first.pid} on host {socket.gethostname()}, "
                                  f"started 20")
        assert f"writing cell {REF}" in message and "run this again, which resumes the cell" in message
    finally:
        os.kill(first.pid, signal.SIGKILL)
        first.wait()
    with writing(cell, cell / "journal.jsonl", REF):  # the kernel released the dead holder's lock
        assert (cell / "writer.lock").read_text().startswith("{")


def test_a_journal_kept_elsewhere_is_locked_as_well(tmp_path):
    journal = tmp_path / "state" / "journal.jsonl"
    assert lock_files(tmp_path / "a", journal) == [tmp_path / "a" / "writer.lock", tmp_path / "state" / "journal.jsonl.lock"]
    assert lock_files(tmp_path / "a", tmp_path / "a" / "journal.jsonl") == [tmp_path / "a" / "writer.lock"]
    first = holder(tmp_path / "a", journal)
    try:
        with pytest.raises(CellLocked, match=rf"{tmp_path / 'state' / 'journal.jsonl.lock'} is locked by pid {first.pid}"):
            with writing(tmp_path / "b", journal, REF):  # another output folder, the same journal
                pass
    finally:
        first.terminate()
        first.wait()


def test_the_lock_is_reentrant_within_its_process_and_released_after_the_outermost_hold(tmp_path):
    with writing(tmp_path, tmp_path / "journal.jsonl", REF):
        with writing(tmp_path, tmp_path / "journal.jsonl", REF):  # `vqb rollout`, then run_cell inside it
            pass
        probe = subprocess.run([sys.executable, "-c", HOLD, str(tmp_path), str(tmp_path / "journal.jsonl"), REF],
                               capture_output=True, text=True, timeout=60)
        assert probe.returncode == 1 and f"is locked by pid {os.getpid()}" in probe.stderr
    assert (tmp_path / "writer.lock").read_text() == ""  # released: no holder named
    second = holder(tmp_path, tmp_path / "journal.jsonl")
    second.terminate()
    second.wait()
