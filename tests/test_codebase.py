"""The shape of the package, checked by reading its source with ``ast``: no class over 250
lines, no function body over 80 lines (docstring included), and no import cycle between the
modules of ``hedger_jax`` (imports inside functions count)."""
import ast
import os

import pytest

PACKAGE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                       "hedger_jax")
MAX_CLASS_LINES = 250
MAX_BODY_LINES = 80


def _modules():
    """{module name: parsed tree} for hedger_jax/*.py ("__init__" for the package)."""
    return {name[:-3]: ast.parse(open(os.path.join(PACKAGE, name)).read(), name)
            for name in sorted(os.listdir(PACKAGE)) if name.endswith(".py")}


def _imports(tree, modules):
    """The package modules a module imports anywhere in its source (``from hedger_jax import
    x`` counts as the submodule x if there is one, else as the package's __init__)."""
    out = set()
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            parts = node.module.split(".")
            if parts[0] != "hedger_jax":
                continue
            names = [parts[1]] if len(parts) > 1 else [
                a.name if a.name in modules else "__init__" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name.split(".")[1] for a in node.names
                     if a.name.startswith("hedger_jax.")]
        out.update(n for n in names if n in modules)
    return out


def _cycles(graph):
    """The strongly connected groups of more than one module (Tarjan), and self-imports."""
    index, low, stack, on, found, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1 or v in graph[v]:
                found.append(sorted(group))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_the_cycle_finder_finds_cycles():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"e"}}
    assert sorted(_cycles(graph)) == [["a", "b", "c"], ["e"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles_in_the_package():
    modules = _modules()
    graph = {name: _imports(tree, modules) - {name} for name, tree in modules.items()}
    assert len(graph) > 20 and "config" in graph["params"]      # the walk sees the imports
    assert _cycles(graph) == []


def _sizes():
    for module, tree in _modules().items():
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                yield "class", f"{module}.{node.name}", node.end_lineno - node.lineno + 1
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield ("function", f"{module}.{node.name}",
                       node.body[-1].end_lineno - node.body[0].lineno + 1)


@pytest.mark.parametrize("kind, limit", [("class", MAX_CLASS_LINES),
                                         ("function", MAX_BODY_LINES)])
def test_no_class_or_function_beyond_its_size(kind, limit):
    sizes = [(name, n) for k, name, n in _sizes() if k == kind]
    assert len(sizes) > 20
    assert [(name, n) for name, n in sizes if n > limit] == []
