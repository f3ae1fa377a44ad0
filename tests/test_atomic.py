"""The one atomic-write helper: all or nothing, and nothing left behind."""

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
