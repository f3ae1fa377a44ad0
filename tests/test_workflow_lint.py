"""`snakemake --lint` on the workflow: the only lint left is the per-rule conda environment or container,
which the project replaces with one locked venv (envs/*.lock.txt). Rule files hold only rules (their
constants and functions live in rules/common.smk), and no path is absolute."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONDA = "Specify a conda environment or container for each rule."


def test_snakemake_lints_nothing_but_conda_environments():
    linted = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "--lint"], cwd=ROOT, capture_output=True,
                            text=True, timeout=300)
    text = linted.stdout + linted.stderr
    linted_rules = re.findall(r"^Lints for rule (\S+)", text, flags=re.M)
    titles = re.findall(r"^    \* (.+?):$", text, flags=re.M)
    assert linted_rules and titles, text[-2000:]  # it did lint the rules
    assert set(titles) == {CONDA}, text[-4000:]
    assert "Lints for snakefile" not in text, text[-4000:]
