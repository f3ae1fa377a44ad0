"""The one atomic-write helper: all or nothing, and nothing left behind."""

import signal
import subprocess
import sys

import pytest

from vlaquantbench.atomic import atomic_write, write_text


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    target = write_text(tmp_path / "sub" / "table.tex", "old\n")
    with pytest.raises(RuntimeError):
        with atomic_write(target) as handle:
            handle.write("half a ta")
            raise RuntimeError("killed mid-write")
    assert target.read_text() == "old\n"
    with atomic_write(target, "wb") as handle:
        handle.write(b"new\n")
    assert target.read_bytes() == b"new\n"
    assert [p.name for p in target.parent.iterdir()] == ["table.tex"]
    assert target.stat().st_mode & 0o777 != 0o600  # ordinary permissions, not mkstemp's private ones


def test_a_writer_killed_mid_write_leaves_a_temporary_that_the_next_write_removes(tmp_path):
    target = write_text(tmp_path / "episodes.parquet", "old\n")
    writer = ("import sys, time; from vlaquantbench.atomic import atomic_write\n"
              "with atomic_write(sys.argv[1]) as handle:\n"
              "    handle.write('half'); handle.flush(); print('writing', flush=True); time.sleep(60)\n")

    def start_writer():
        process = subprocess.Popen([sys.executable, "-c", writer, str(target)], stdout=subprocess.PIPE, text=True)
        assert process.stdout.readline() == "writing\n"
        return process

    killed, alive = start_writer(), start_writer()
    killed.send_signal(signal.SIGKILL)
    killed.wait()
    temporaries = lambda: sorted(p.name for p in tmp_path.iterdir() if p.name != "episodes.parquet")  # noqa: E731
    assert len(temporaries()) == 2
    alive_tmp = [name for name in temporaries() if f".{alive.pid}-" in name]
    write_text(target, "new\n")
    assert target.read_text() == "new\n"
    assert temporaries() == alive_tmp  # the dead writer's is gone; the live one's is kept
    alive.kill()
    alive.wait()
