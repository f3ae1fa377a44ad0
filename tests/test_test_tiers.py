"""Test tiers: `pytest -m "not slow"` is the inner loop, so every test that runs a simulator episode, a
Snakemake workflow or training must be marked `slow`. Checked statically, per test file: a test that
reaches (through the file's own helpers and fixtures, and those of conftest.py) a call that runs episodes,
builds a simulator env, trains, records demonstrations or runs Snakemake without `-n` must carry
`@pytest.mark.slow` (or its module `pytestmark`, or its class's mark). The tiers' measured times are in
benchmarks/results/test_tiers.json."""

import ast
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
# Calls that run a simulator episode, start simulator workers, calibrate in closed loop, train or record.
SLOW_CALLS = {
    "run_cell", "run_episodes", "calibrate", "make_env", "LiberoVectorEnv", "MetaworldVectorEnv",
    "train_policy", "write_demonstrations", "run_snakemake",
}
# Tests that reach a slow call only to see it refused before anything starts (seconds): file -> test -> why.
FAST_REFUSALS = {
    "test_training.py": {
        "test_a_captured_step_is_refused_where_it_cannot_run_before_the_dataset_loads":
            "train_policy refuses the settings before it reads the dataset",
    },
    "test_libero_suite.py": {
        "test_bad_names_and_indices_are_user_errors": "LiberoVectorEnv(num_envs=0) is refused before a worker starts",
        "test_other_mujoco_versions_are_refused_unless_overridden": "the MuJoCo pin is checked before a worker starts",
    },
}
# String arguments that make a Snakemake invocation plan only, not run jobs.
DRY = {"-n", "--dry-run", "--dryrun", "--lint", "--list", "-l", "--summary", "--detailed-summary", "--dag",
       "--rulegraph", "--list-target-rules", "--help", "--version", "--unlock"}


def _name(node: ast.AST) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def _strings(node: ast.AST) -> set[str]:
    return {n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)}


def _runs_snakemake(call: ast.Call, function: ast.AST) -> bool:
    """A call whose arguments name snakemake (a binary or `-m snakemake`) with no dry-run flag in the function."""
    spawns = _name(call.func) in ("run", "Popen", "check_output", "check_call", "call")
    scope = function if spawns else call  # a subprocess's argv is often built beside it (`cmd = [...]`)
    words = _strings(scope)
    names = {_name(n) for n in ast.walk(scope)}
    if not (any(w.split("/")[-1] == "snakemake" for w in words) or "SNAKEMAKE" in names):
        return False
    return not (_strings(function) & DRY)


def _is_slow_mark(node: ast.AST) -> bool:
    return any(isinstance(n, ast.Attribute) and n.attr == "slow" for n in ast.walk(node))


class Module:
    def __init__(self, path: Path):
        self.tree = ast.parse(path.read_text(), str(path))
        self.functions = {n.name: n for n in ast.walk(self.tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
        self.module_slow = any(
            isinstance(n, ast.Assign) and any(_name(t) == "pytestmark" for t in n.targets) and _is_slow_mark(n.value)
            for n in self.tree.body)

    def direct(self, function: ast.AST) -> tuple[bool, set[str]]:
        """Whether `function` itself makes a slow call, and the names it calls or requests as fixtures."""
        reached = {a.arg for a in function.args.args}
        slow = False
        for node in ast.walk(function):
            if isinstance(node, ast.Call):
                name = _name(node.func)
                if not ({a.value for a in node.args if isinstance(a, ast.Constant)} & DRY):
                    reached.add(name)  # a helper called with `-n` plans only
                reached.update(_name(a) for a in node.args)  # functions passed on (e.g. to a pool)
                if name in SLOW_CALLS or _runs_snakemake(node, function):
                    slow = True
                # CellRun(...).prepare() loads a policy (seconds); its .run() runs the cell's episodes.
                if (isinstance(node.func, ast.Attribute) and node.func.attr == "run"
                        and not (isinstance(node.func.value, ast.Name) and node.func.value.id == "subprocess")
                        and any(_name(n.func) == "CellRun" for n in ast.walk(function) if isinstance(n, ast.Call))):
                    slow = True
        local = {n.id for n in ast.walk(function) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}
        return slow, {r for r in reached if r and r not in local}


def slow_closure(test: ast.AST, modules: list[Module]) -> bool:
    seen, todo = set(), [test]
    while todo:
        function = todo.pop()
        if id(function) in seen:
            continue
        seen.add(id(function))
        module = next(m for m in modules if function in m.functions.values())
        slow, names = module.direct(function)
        if slow:
            return True
        for name in names:
            for m in modules:
                if name in m.functions and m.functions[name] is not function:
                    todo.append(m.functions[name])
    return False


def unmarked_slow_tests(path: Path) -> list[str]:
    module, conftest = Module(path), Module(TESTS / "conftest.py")
    if module.module_slow:
        return []
    found = []
    for node in module.tree.body:
        tests = []
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name.startswith("test"):
            tests.append((node, []))
        elif isinstance(node, ast.ClassDef) and node.name.startswith("Test"):
            tests += [(n, node.decorator_list) for n in node.body
                      if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.name.startswith("test")]
        for test, outer in tests:
            if any(_is_slow_mark(d) for d in [*outer, *test.decorator_list]):
                continue
            if test.name in FAST_REFUSALS.get(path.name, {}):
                continue
            if slow_closure(test, [module, conftest]):
                found.append(test.name)
    return found


TEST_FILES = [path for path in sorted(TESTS.glob("test_*.py")) if path.name != Path(__file__).name]


@pytest.mark.parametrize("path", TEST_FILES, ids=lambda p: p.name)
def test_each_test_that_runs_episodes_a_workflow_or_training_is_marked_slow(path):
    assert unmarked_slow_tests(path) == [], f"{path.name}: mark these @pytest.mark.slow"


def test_the_check_sees_a_slow_call_and_a_dry_run(tmp_path):
    sample = tmp_path / "test_sample.py"
    sample.write_text(
        "import subprocess, pytest\n"
        "from vlaquantbench.runner.cell import run_cell\n"
        "def helper(cfg):\n    return run_cell(cfg)\n"
        "def test_runs(tmp_path):\n    helper(None)\n"
        "@pytest.mark.slow\ndef test_marked():\n    run_cell(None)\n"
        "def test_workflow():\n    subprocess.run(['snakemake', '--cores', '1'])\n"
        "def test_dry():\n    subprocess.run(['snakemake', '-n'])\n"
        "def test_fast():\n    assert 1\n")
    assert unmarked_slow_tests(sample) == ["test_runs", "test_workflow"]
