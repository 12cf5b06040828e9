"""The package's imports form no circle (issue 51): every module's imports, read with ``ast`` (imports inside
functions included), make a graph over the package's modules, and no strongly connected component may hold more
than one module, apart from the known exceptions listed below, each with the issue that removes it."""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "torchrl_options"

KNOWN_CYCLES = []


def _modules() -> dict[str, Path]:
    modules = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    return modules


def import_graph() -> dict[str, set[str]]:
    """``{module: the package's modules it imports}``; ``from pkg import name`` counts as an import of
    ``pkg.name`` when that is a module, else of ``pkg``."""
    modules = _modules()
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                graph[name] |= {a.name for a in node.names if a.name in modules}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative: from .x import y
                    parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(parts + ([base] if base else []))
                if base != "torchrl_options" and not base.startswith("torchrl_options."):
                    continue
                for alias in node.names:
                    target = f"{base}.{alias.name}"
                    graph[name].add(target if target in modules else base)
    return {name: {t for t in targets if t in modules and t != name} for name, targets in graph.items()}


def cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[set[str]] = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = set()
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.add(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(component)
    return found


def test_the_cycle_finder_finds_a_circle_through_an_in_function_import():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [{"a", "b", "c"}]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_graph_reads_imports_inside_functions():
    graph = import_graph()
    # hierarchy.OptionHierarchy.executors imports the transforms inside the method
    assert "torchrl_options.transforms" in graph["torchrl_options.hierarchy.hierarchy"]
    assert "torchrl_options.discovery.validation" in graph["torchrl_options.discovery.initialization"]


def test_no_import_cycles_in_the_package():
    found = cycles(import_graph())
    unexpected = [sorted(c) for c in found if c not in KNOWN_CYCLES]
    assert not unexpected, f"import cycles: {unexpected}"


@pytest.mark.parametrize("known", KNOWN_CYCLES, ids=lambda c: "-".join(sorted(m.rsplit(".", 1)[1] for m in c)))
def test_known_cycles_are_still_there(known):
    """A known exception that is gone must leave the list (so the list stays true)."""
    assert known in cycles(import_graph())


def private_imports_in(name: str, source: str) -> list[tuple[str, str, str]]:
    """``(module, imported module, name)`` for every private name (or name from a private module) that the module
    ``name`` of source ``source`` imports from another module of the package, imports inside functions included."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("torchrl_options") and not node.level:
            private_module = any(part.startswith("_") for part in node.module.split(".")[1:])
            for alias in node.names:
                if node.module != name and (private_module or alias.name.startswith("_")):
                    found.append((name, node.module, alias.name))
    return found


def private_imports(subpackage: str) -> list[tuple[str, str, str]]:
    """:func:`private_imports_in` over the modules of ``torchrl_options.<subpackage>``."""
    return [
        found
        for name, path in _modules().items()
        if name.startswith(f"torchrl_options.{subpackage}")
        for found in private_imports_in(name, path.read_text())
    ]


def test_private_imports_are_found():
    source = "from torchrl_options.a import b, _c\ndef f():\n    from torchrl_options._d import e\n"
    assert private_imports_in("torchrl_options.x", source) == [
        ("torchrl_options.x", "torchrl_options.a", "_c"),
        ("torchrl_options.x", "torchrl_options._d", "e"),
    ]


@pytest.mark.parametrize("subpackage", ["transforms"])
def test_no_private_imports(subpackage):
    """What a module shares with another is public (issue 51 part 3): no ``from module import _name``."""
    assert private_imports(subpackage) == []
