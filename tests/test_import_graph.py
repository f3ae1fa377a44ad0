"""The package's import graph between subpackages is a DAG (issue 14: models -> accel -> quant ->
models was a cycle). Every import counts, including those inside functions, because a function-level
import is still a dependency: the file is parsed with `ast` and every Import/ImportFrom node anywhere
in it is collected. Top-level modules (`cells.py`, `errors.py`, ...) are nodes of their own."""

import ast
from pathlib import Path

import networkx as nx

import vlaquantbench

PACKAGE = Path(vlaquantbench.__file__).parent


def _node(module: str) -> str:
    """`vlaquantbench.quant.apply` -> `quant`; `vlaquantbench.cells` -> `cells`."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "vlaquantbench"


def _imported_modules(path: Path, module: str) -> set[str]:
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            found.add(".".join([*base, *([node.module] if node.module else [])]))
    return {m for m in found if m == "vlaquantbench" or m.startswith("vlaquantbench.")}


def import_graph() -> nx.DiGraph:
    graph = nx.DiGraph()
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        module = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        source = _node(module)
        graph.add_node(source)
        for target in map(_node, _imported_modules(path, module)):
            if target != source:
                graph.add_edge(source, target, file=str(path.relative_to(PACKAGE)))
    return graph


def test_no_cycle_between_subpackages():
    graph = import_graph()
    assert {"models", "quant", "runner"} <= set(graph)  # the walk found the package
    cycles = list(nx.simple_cycles(graph))
    described = [" -> ".join([*c, c[0]]) + " (" + ", ".join(graph.edges[a, b]["file"] for a, b in zip(c, [*c[1:], c[0]])) + ")"
                 for c in cycles]
    assert not cycles, "import cycles between subpackages: " + "; ".join(described)


def test_imports_inside_functions_and_relative_imports_are_collected(tmp_path):
    source = tmp_path / "vlaquantbench" / "runner" / "example.py"
    source.parent.mkdir(parents=True)
    source.write_text(
        "import os\n"
        "from . import journal\n"
        "from ..quant.apply import quantize_\n"
        "def run():\n"
        "    class Later:\n"
        "        def go(self):\n"
        "            from vlaquantbench.models.pi05 import fast\n"
        "            import vlaquantbench.records\n"
    )
    found = _imported_modules(source, "vlaquantbench.runner.example")
    assert found == {"vlaquantbench.runner", "vlaquantbench.quant.apply", "vlaquantbench.models.pi05",
                     "vlaquantbench.records"}
    assert {_node(m) for m in found} == {"runner", "quant", "models", "records"}
