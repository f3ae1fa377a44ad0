"""The package's import graph is a DAG, between subpackages (issue 14: models -> accel -> quant ->
models was a cycle) and between modules (issue 50: quant.fused_kernel -> hooks -> transforms -> rotation,
records.authors <-> records.cell). Every import counts, including those inside functions, because a function-level
import is still a dependency: the file is parsed with `ast` and every Import/ImportFrom node anywhere
in it is collected, and so does one under `if TYPE_CHECKING:` (a circle for a type checker, and one
import away from a circle at run time). Top-level modules (`cells.py`, `errors.py`, ...) are nodes of their own."""

import ast
from pathlib import Path

import networkx as nx

import vlaquantbench

PACKAGE = Path(vlaquantbench.__file__).parent


def _node(module: str) -> str:
    """`vlaquantbench.quant.apply` -> `quant`; `vlaquantbench.cells` -> `cells`."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "vlaquantbench"


def _imported_modules(path: Path, module: str, modules: frozenset[str] = frozenset()) -> set[str]:
    """The package's modules that `path` (module `module`) imports. `from x import y` imports module
    `x.y` where `modules` (the package's modules) has it, else `x`."""
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            source = ".".join([*base, *([node.module] if node.module else [])])
            found.update(f"{source}.{alias.name}" if f"{source}.{alias.name}" in modules else source
                         for alias in node.names)
    return {m for m in found if m == "vlaquantbench" or m.startswith("vlaquantbench.")}


def _modules() -> dict[str, Path]:
    modules = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def module_graph() -> nx.DiGraph:
    """Module -> the package's modules it imports."""
    modules = _modules()
    graph = nx.DiGraph()
    for module, path in modules.items():
        graph.add_node(module)
        graph.add_edges_from((module, target) for target in _imported_modules(path, module, frozenset(modules))
                             if target != module and target in modules)
    return graph


def import_graph() -> nx.DiGraph:
    graph = nx.DiGraph()
    for module, path in _modules().items():
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


def test_no_cycle_between_modules():
    graph = module_graph()
    assert {"vlaquantbench.quant.hooks", "vlaquantbench.records.cell"} <= set(graph)
    assert graph.has_edge("vlaquantbench.quant.hooks", "vlaquantbench.quant.fused_kernel")  # a function-level import
    cycles = sorted(" -> ".join([*c, c[0]]) for c in nx.simple_cycles(graph))
    assert not cycles, "import cycles between modules: " + "; ".join(cycles)


def test_a_circle_through_a_type_checking_import_is_found(tmp_path):
    package = tmp_path / "vlaquantbench" / "quant"
    package.mkdir(parents=True)
    (package / "a.py").write_text("from vlaquantbench.quant import b\n")
    (package / "b.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from vlaquantbench.quant.a import X\n")
    modules = frozenset({"vlaquantbench.quant", "vlaquantbench.quant.a", "vlaquantbench.quant.b"})
    assert _imported_modules(package / "a.py", "vlaquantbench.quant.a", modules) == {"vlaquantbench.quant.b"}
    assert _imported_modules(package / "b.py", "vlaquantbench.quant.b", modules) == {"vlaquantbench.quant.a"}


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
