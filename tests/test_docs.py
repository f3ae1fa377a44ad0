"""User documentation: the README stays short and free of issue numbers, the mkdocs site builds with
`--strict` (no broken links, no missing references), and its generated pages (configuration reference,
results) are what `docs/gen_pages.py` writes from the schemas and the committed results files."""

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
USER_DOCS = [ROOT / "README.md", ROOT / "benchmarks" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def gen_pages():
    spec = importlib.util.spec_from_file_location("gen_pages", ROOT / "docs" / "gen_pages.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_readme_is_at_most_200_lines_with_the_sections_others_read():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 200
    for heading in ("## Set up and run", "## What you can do with it", "## Plug-in seams", "## Documentation"):
        assert heading in readme


@pytest.mark.parametrize("path", USER_DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_user_documentation_names_no_issue_and_no_dated_investigation(path):
    text = path.read_text()
    assert not re.search(r"\bissues? #?\d+", text, re.IGNORECASE), "issue numbers belong in HISTORY.md"
    assert not re.search(r"\(\w+ \d+ item \d+\)", text)
    if path.name != "results.md":  # generated: its dates are the results files'
        assert not re.search(r"\b20\d\d-[01]\d-[0-3]\d\b", text), "dates belong in the results files"


COMMITTED = ("src/", "benchmarks/", "config/", "tests/", "manifests/", "checkpoints/", "scripts/", "profiles/",
             "envs/", "workflow/", "rules/", "docs/")


@pytest.mark.parametrize("path", USER_DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_committed_file_the_documentation_names_exists(path):
    """Paths of the checkout in code spans (outputs under results/ and placeholders aside) exist."""
    missing = []
    for token in re.findall(r"`([^`\s]+)`", path.read_text()):
        token = token.rstrip(".,;:)").split("::")[0]
        if token.startswith(COMMITTED) and not any(c in token for c in "<>{}*[]…") and "..." not in token:
            if not (ROOT / token).exists():
                missing.append(token)
    assert not missing, f"{path.name} names files that do not exist: {missing}"


def test_the_generated_pages_are_committed_as_generated():
    module = gen_pages()
    for name, make in module.PAGES.items():
        assert (ROOT / "docs" / name).read_text() == make() + "\n", f"docs/{name} is stale: python docs/gen_pages.py"


def test_the_configuration_reference_covers_every_key_of_every_schema():
    module = gen_pages()
    page = (ROOT / "docs" / "configuration.md").read_text()
    files = module.schema_files()
    assert {path.name for path in files} >= {"config.schema.yaml", "table.schema.yaml", "figure.schema.yaml",
                                             "cohort.schema.yaml", "scopes.schema.yaml", "replay_study.schema.yaml",
                                             "episode.schema.yaml", "record_header.schema.yaml"}
    documented = set(re.findall(r"^\| `([^`]+)` \|", page, re.MULTILINE))
    last_parts = {key.rsplit(".", 1)[-1].removesuffix("[]") for key in documented}
    for path in files:
        assert f"`{path.relative_to(ROOT)}`" in page
        missing = module.schema_keys(yaml.safe_load(path.read_text())) - last_parts
        assert not missing, f"{path.name}: keys missing from docs/configuration.md: {sorted(missing)}"


def test_the_configuration_reference_has_the_nested_study_keys():
    page = (ROOT / "docs" / "configuration.md").read_text()
    for key in ("study.models.<name>.trained", "study.sequential", "study.execution"):
        assert f"`{key}`" in page or any(line.startswith(f"| `{key}.") for line in page.splitlines()), key


def test_the_results_page_names_the_files_its_figures_come_from():
    page = (ROOT / "docs" / "results.md").read_text()
    assert "`benchmarks/results/summary.json`" in page and "`benchmarks/results/test_tiers.json`" in page
    import json
    for key in json.loads((ROOT / "benchmarks/results/summary.json").read_text()):
        assert f"### `{key}`" in page
    # The study tables are rendered from their committed records, not typed in.
    assert '<table id="tab:methods_2026">' in page and '<table id="tab:trained_sequential">' in page
    assert "`results/methods_2026`" in page and "`manifests/trained_sequential_live.tsv`" in page


def test_mkdocs_builds_the_site_strictly(tmp_path):
    mkdocs = BIN / "mkdocs"
    if not mkdocs.exists():
        pytest.fail("mkdocs is not installed: scripts/setup.sh installs the test extra, which includes docs")
    result = subprocess.run(
        [str(mkdocs), "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
        env={"PATH": f"{BIN}:/usr/bin:/bin", "NO_MKDOCS_2_WARNING": "1",
             "PYTHONPATH": str(ROOT / "src"), "HOME": str(tmp_path)},
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "WARNING" not in result.stderr, result.stderr
    api = (tmp_path / "site" / "api" / "index.html").read_text()
    for page in (tmp_path / "site").rglob("*.html"):  # the API reference's docstrings included
        assert not re.search(r"\bissues? #?\d+", page.read_text(), re.IGNORECASE), page
    assert "sequential" in api and "doc-" in api  # mkdocstrings rendered the modules' docstrings
    for page in ("configuration", "results", "getting-started", "sequential", "cluster", "checkpoints",
                 "simulators", "extending", "cells"):
        assert (tmp_path / "site" / page / "index.html").exists(), page


def test_every_benchmark_script_has_a_row_with_its_command_in_benchmarks_readme():
    readme = (ROOT / "benchmarks" / "README.md").read_text()
    rows = [line for line in readme.splitlines() if line.startswith("| `")]
    scripts = [p for p in sorted((ROOT / "benchmarks").iterdir()) if p.suffix in (".py", ".sh")]
    for script in scripts:
        if script.name == "simstack.py":  # the packer the GPU scripts run on; its own paragraph and test
            assert "benchmarks/simstack.py" in readme
            continue
        row = next((line for line in rows if f"`{script.name}`" in line.split("|")[1]), None)
        assert row is not None, f"benchmarks/{script.name} has no row in benchmarks/README.md"
        command = row.split("|")[3]
        runner = "gpu_train_policy.sh" if script.name == "gpu_train_step.py" else script.name  # the call runs it
        assert runner in command, f"benchmarks/{script.name}: its row gives no command that runs it"
