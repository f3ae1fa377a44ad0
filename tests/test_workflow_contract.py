"""The workflow contract (issue 14 §3): every rule logs under logs/, its jobs touch only the files it
declares, parsing imports no torch, a refused run leads with its cause and leaves no stale table behind."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from snakemake.api import SnakemakeApi
from snakemake.settings.types import ConfigSettings, OutputSettings, ResourceSettings

from file_audit import audited_env, job_audits, undeclared
from paths import ROOT, SHARED


def reference_checkout(tmp_path: Path) -> Path:
    """A workdir whose `../shared` and `manifests/` are the real ones, as config/reference.yaml expects."""
    workdir = tmp_path / "checkout"
    workdir.mkdir()
    (workdir / "manifests").symlink_to(ROOT / "manifests")
    (tmp_path / "shared").symlink_to(SHARED)
    return workdir


def snakemake(workdir: Path, *args: str, python_flags: tuple[str, ...] = (), snakefile: Path = ROOT / "Snakefile",
              env: dict[str, str] | None = None, timeout: int = 300) -> subprocess.CompletedProcess:
    command = [sys.executable, *python_flags, "-m", "snakemake", *args, "--cores", "1",
               "--snakefile", str(snakefile), "--directory", str(workdir)]  # fmt: skip
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=env)


UNDECLARED_ACCESS = """
rule honest:
    input: "given.txt"
    output: "made.txt"
    log: "logs/honest.log"
    script: "job.py"

rule sneaky:
    input: "given.txt"
    output: "also_made.txt"
    log: "logs/sneaky.log"
    script: "job.py"
"""
JOB = """
import os
from pathlib import Path
from vlaquantbench.atomic import write_text
sm = snakemake  # noqa: F821
Path(sm.log[0]).write_text("ran")
write_text(sm.output[0], Path(sm.input[0]).read_text())
if sm.rule == "sneaky":
    Path("beside.txt").write_text("not declared")
    Path("secret.txt").read_text()
    os.listdir("folder")
"""


@pytest.mark.slow
def test_the_audit_names_every_file_a_job_touches_undeclared(tmp_path):
    """The check below can fail: a job that writes, reads or lists what its rule does not declare is caught."""
    workdir = tmp_path / "work"
    (workdir / "folder").mkdir(parents=True)
    for name, text in {"given.txt": "x", "secret.txt": "y", "Snakefile": UNDECLARED_ACCESS, "job.py": JOB}.items():
        (workdir / name).write_text(text)
    audit = tmp_path / "audit"
    run = snakemake(workdir, "made.txt", "also_made.txt", snakefile=workdir / "Snakefile", env=audited_env(audit))
    assert run.returncode == 0, run.stderr[-3000:]
    assert sorted(job["rule"] for job in job_audits(audit)) == ["honest", "sneaky"]
    real = workdir.resolve()
    assert undeclared(audit, workdir) == {
        "sneaky": [f"list {real / 'folder'}", f"read {real / 'secret.txt'}", f"write {real / 'beside.txt'}"]
    }


@pytest.mark.slow
def test_reference_rules_touch_exactly_their_declared_files(tmp_path):
    """Every rule the reference config runs (records and authors' files, no GPU) in a real Snakemake run;
    paper_table's jobs are audited in the refused-run test below."""
    workdir, audit = reference_checkout(tmp_path), tmp_path / "audit"
    targets = ["tables/summary.csv", "tables/vla_params.tex", "tables/proxy_audit.tex",
               "tables/replay_composition.tex", "tables/replay_all_formats.tex", "tables/replay_bias.tex",
               "figures/replay_formats.pdf", "figures/scope_recovery.pdf"]
    run = snakemake(workdir, *targets, f"--configfile={ROOT / 'config' / 'reference.yaml'}", env=audited_env(audit),
                    timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    assert {job["rule"] for job in job_audits(audit)} == {
        "summary", "vla_params_table", "proxy_audit_table", "replay_composition_table",
        "replay_all_formats_table", "replay_bias_table", "replay_formats_figure", "scope_recovery_figure"}
    assert undeclared(audit, workdir) == {}


def test_every_rule_that_runs_something_logs_under_logs(tmp_path):
    with SnakemakeApi(OutputSettings()) as api:
        workflow = api.workflow(
            resource_settings=ResourceSettings(cores=1),
            config_settings=ConfigSettings(configfiles=[ROOT / "config" / "config.yaml"]),
            snakefile=ROOT / "Snakefile",
            workdir=tmp_path,
        )._workflow
        rules = {rule.name: rule for rule in workflow.rules}
    runs_something = {name: rule for name, rule in rules.items() if not rule.norun}
    assert {"rollout", "calibrate", "download_checkpoint", "paper_table", "replay_record"} <= set(runs_something)
    assert rules["all"].norun
    for name, rule in runs_something.items():
        assert len(rule.log) == 1 and str(rule.log[0]).startswith("logs/"), (name, list(rule.log))


@pytest.mark.parametrize(("configfile", "planned"), [("config.yaml", "rollout"), ("reference.yaml", "paper_table")])
def test_dry_run_imports_no_torch(tmp_path, configfile, planned):
    run = snakemake(reference_checkout(tmp_path), "-n", "tables/lattice.tex", f"--configfile={ROOT / 'config' / configfile}",
                    python_flags=("-X", "importtime"))  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    imported = {line.rsplit("|", 1)[1].strip() for line in run.stderr.splitlines() if line.startswith("import time:")}
    assert "snakemake.dag" in imported and "vlaquantbench.workflow" in imported  # the DAG was really built
    assert not {m for m in imported if m == "torch" or m.startswith("torch.")}
    assert planned in run.stdout


@pytest.mark.slow
def test_refused_run_leads_with_its_cause_and_removes_the_stale_table(tmp_path):
    workdir = reference_checkout(tmp_path)
    config = f"--configfile={ROOT / 'config' / 'reference.yaml'}"
    audit = tmp_path / "audit"
    assert snakemake(workdir, "tables/lattice.tex", config, env=audited_env(audit)).returncode == 0
    table = workdir / "tables" / "lattice.tex"
    assert table.is_file()
    assert [job["rule"] for job in job_audits(audit)] == ["paper_table"]
    assert undeclared(audit, workdir) == {}  # its records and their manifest, its table and page, its log

    lines = (ROOT / "manifests" / "reference.tsv").read_text().splitlines()
    changed = "libero/libero_spatial/pi05/ablate-W4A4-ah-attn_adarms.jsonl"  # a record tab:lattice reads
    bad = tmp_path / "bad.tsv"
    def with_zero_sha(line: str) -> str:
        fields = line.split("\t")
        fields[3] = "0" * 64  # path, episodes, successes, sha256, ...
        return "\t".join(fields)

    bad.write_text("\n".join(with_zero_sha(line) if line.startswith(changed) else line for line in lines) + "\n")
    run = snakemake(workdir, "tables/lattice.tex", config, "--config", f"manifest={bad}")
    assert run.returncode != 0
    cause = f"{changed} does not match manifest {bad} (SHA-256 differs"
    console = run.stderr
    assert f"paper_table failed: record ../shared/reference/records/{cause}" in console
    # ... and again as the last words of the run, with the log that holds the traceback.
    tail = console[console.index("The run stopped because:"):]
    assert "paper_table: record" in tail and cause in tail and "(log: logs/tables/lattice.log)" in tail
    log = (workdir / "logs" / "tables" / "lattice.log").read_text()
    assert "Traceback" in log and log.splitlines()[-1].startswith("error: record") and "Traceback" not in console
    assert not table.exists()  # refused: the earlier run's table is not left looking current


def test_mujoco_warnings_go_to_stderr_not_to_a_file_in_the_working_folder(tmp_path):
    script = """
import mujoco, numpy as np
from vlaquantbench.envs.libero import load_libero
load_libero()
model = mujoco.MjModel.from_xml_string('<mujoco><worldbody><body><joint/><geom size=".1"/></body></worldbody></mujoco>')
data = mujoco.MjData(model)
data.qvel[:] = np.nan
mujoco.mj_step(model, data)
"""
    run = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "MuJoCo warning: Nan, Inf or huge value in QVEL" in run.stderr
    assert list(tmp_path.iterdir()) == []  # no MUJOCO_LOG.TXT
