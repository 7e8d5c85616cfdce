"""No import circle in the package: module A imports B (anywhere in A, inside functions too)
and B, directly or through others, imports A."""
from __future__ import annotations

from pathlib import Path

from test_layers import PACKAGE, imports_of, module_name


def import_graph(package: Path) -> dict[str, set[str]]:
    """Module -> the package's modules it imports."""
    graph: dict[str, set[str]] = {}
    for path in sorted(package.rglob("*.py")):
        module = module_name(path, package)
        graph[module] = {target for _, target in imports_of(path, module, package)
                         if target.split(".")[0] == package.name and target != module}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (Tarjan's algorithm), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        on_stack.add(module)
        for target in graph.get(module, ()):
            if target not in index:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in on_stack:
                low[module] = min(low[module], index[target])
        if low[module] == index[module]:
            group = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                group.append(member)
                if member == module:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return found


def test_the_package_has_no_import_circle():
    assert cycles(import_graph(PACKAGE)) == []


def test_a_circle_through_a_function_level_import_is_found(tmp_path):
    pkg = tmp_path / "hdrqn_ros"
    (pkg / "nodes").mkdir(parents=True)
    for init in (pkg / "__init__.py", pkg / "nodes" / "__init__.py"):
        init.write_text("")
    (pkg / "nodes" / "process.py").write_text("def make():\n    from hdrqn_ros.nodes import acting\n")
    (pkg / "nodes" / "acting.py").write_text("from hdrqn_ros.nodes.process import make\n")
    (pkg / "nodes" / "other.py").write_text("from hdrqn_ros.nodes import process\n")
    assert cycles(import_graph(pkg)) == [["hdrqn_ros.nodes.acting", "hdrqn_ros.nodes.process"]]
