"""Which files a Snakemake job touched that its rule does not declare (the workflow contract, issue 14 §3:
declared inputs and outputs are exactly the files the scripts read and write).

    env = audited_env(tmp_path / "audit")          # run snakemake with this environment
    assert undeclared(tmp_path / "audit", workdir) == {}

Only data files count: those under the Snakemake working folder (minus its .snakemake/ bookkeeping)
and under ../shared; the project's code and definitions (src/, config/, workflow/, rules/, Snakefile)
are read by name, Python's import system lists the folders on sys.path, and libraries probe for
folders that do not exist (torch's CUDA library search). A job may read its declared inputs, outputs
and logs, and write its outputs, logs and `params.state` files (a rollout's journal, which must survive
a failed job); the hidden temporary file of an atomic write counts as its target, and listing the
folder it writes in is its clean-up. Listing any other folder is never declared.
"""

from __future__ import annotations

import functools
import json
import os
import re
import socket
from pathlib import Path

from paths import ROOT, SHARED

AUDIT_SITE = Path(__file__).with_name("audit_site")
CODE = ("src", "config", "workflow", "rules", "Snakefile")  # in the checkout, or in a copy of it
# vlaquantbench.atomic's temporary files: `.<name>.<host>.<pid>-<thread>.tmp`
_ATOMIC_TMP = re.compile(rf"^\.(?P<name>.+)\.{re.escape(socket.gethostname())}\.\d+-\d+\.tmp$")


def audited_env(audit_dir: Path) -> dict[str, str]:
    """The environment of a Snakemake run whose job scripts record the files they touch in `audit_dir`."""
    audit_dir.mkdir(parents=True, exist_ok=True)
    path = os.pathsep.join(p for p in (str(AUDIT_SITE), os.environ.get("PYTHONPATH")) if p)
    return {**os.environ, "PYTHONPATH": path, "VQB_FILE_AUDIT": str(audit_dir)}


def _real(path: str | Path) -> Path:
    real = Path(os.path.realpath(path))
    match = _ATOMIC_TMP.match(real.name)
    return real.with_name(match["name"]) if match else real


def _within(path: Path, folders: list[Path]) -> bool:
    # By string prefix (both sides resolved): `folder in path.parents` builds a Path per level, and a
    # job's audit holds ~10^4 events.
    text = str(path)
    return any(text == str(folder) or text.startswith(str(folder).rstrip(os.sep) + os.sep) for folder in folders)


def job_audits(audit_dir: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(audit_dir.glob("*.json"))]


def undeclared(audit_dir: Path, workdir: Path) -> dict[str, list[str]]:
    """`<rule>` -> sorted `<action> <path>` of every data file a job of the rule touched undeclared."""
    real = functools.cache(_real)  # one realpath per distinct path: every job imports the same modules
    data = [real(workdir), real(SHARED)]
    skip = [real(workdir / ".snakemake"), *(real(top / name) for top in (ROOT, workdir) for name in CODE)]
    found: dict[str, set[str]] = {}
    for job in job_audits(audit_dir):
        declared = {kind: {real(p) for p in paths} for kind, paths in job["declared"].items()}
        may_read = declared["input"] | declared["output"] | declared["log"] | declared["state"]
        may_write = declared["output"] | declared["log"] | declared["state"]
        import_path = {real(p) for p in job["import_path"]}  # Python's import system lists these
        # atomic_write lists the folder of the file it writes, to remove a killed writer's temporary files
        write_folders = {path.parent for path in may_write}
        for action, raw in {tuple(event) for event in job["events"]}:  # a repeated event: one verdict
            path = real(raw)
            if not _within(path, data) or _within(path, skip):
                continue
            if action == "list" and (path in import_path | write_folders or not path.is_dir()):
                continue  # the import system, atomic_write's clean-up, a library probing for folders
            allowed = {"read": may_read, "write": may_write, "remove": may_write, "list": set()}[action]
            if path not in allowed:
                found.setdefault(job["rule"], set()).add(f"{action} {path}")
    return {rule: sorted(paths) for rule, paths in found.items()}
