"""The commands of the README's "What you can do with it" table work as written: every Snakemake command
builds its DAG (a dry run, `-n`, with the table's own targets, profile and config files), and every `vqb`
command without a placeholder runs (`vqb rollout` with the `--show` the table names: nothing rolled out).
The placeholder DIR of "your own records" is the authors' records folder; rows that write a report or
name FILE, CELL or a folder of one's own are left to the tests of those commands; optional arguments
in brackets are left out."""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from paths import REFERENCE

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
PLACEHOLDERS = ("DIR", "FILE", "CELL")


def table_commands() -> list[str]:
    readme = (ROOT / "README.md").read_text()
    start = readme.index("## What you can do with it")
    section = readme[start:readme.index("\n## ", start)]
    commands = []
    for row in section.splitlines():
        if row.startswith("| ") and "`" in row:
            cells = [cell for cell in re.findall(r"`([^`]+)`", row.split("|")[-2]) if not cell.startswith("--")]
            shows = "`--show`" in row
            commands += [f"{command} --show" if shows else command for command in cells]
    return commands


def runnable(command: str) -> tuple[dict[str, str], list[str]] | None:
    """The environment and argv of `command` as this test runs it, or None for a row it leaves alone."""
    env = {}
    if "&&" in command:  # the hub fixture's row: the Snakemake half (its DAG needs no fixture)
        command = command.split("&&", 1)[1].strip()
    command = re.sub(r"\s*\[[^]]*\]", "", command)  # optional arguments, as in `vqb methods [--json]`
    command = command.replace("records_dir=DIR", f"records_dir={REFERENCE / 'records'}")
    words = shlex.split(command)
    while "=" in words[0] and not words[0].startswith("-"):
        key, value = words.pop(0).split("=", 1)
        env[key] = value
    if any(mark in command for mark in ("--report", *PLACEHOLDERS)) or words[0] not in ("snakemake", "vqb"):
        return None
    argv = [str(BIN / words[0]), *words[1:]]
    if words[0] == "snakemake":
        argv.insert(1, "-n")
    return env, argv


COMMANDS = [command for command in table_commands() if runnable(command) is not None]


def test_the_table_has_the_commands_this_test_runs():
    assert len(table_commands()) >= 18 and len(COMMANDS) >= 15


@pytest.mark.parametrize("command", COMMANDS)
def test_a_readme_command_runs_as_written(command, tmp_path):
    env, argv = runnable(command)
    done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=600,
                          env={**os.environ, **env, "HOME": str(tmp_path)})
    output = done.stdout + done.stderr
    assert done.returncode == 0, output[-3000:]
    if argv[1] == "-n":
        assert re.search(r"This was a dry-run|Nothing to be done", output), output[-3000:]
