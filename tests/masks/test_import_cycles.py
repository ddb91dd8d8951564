"""The modules of masks/ import each other without cycles (lazy imports inside functions count)."""

import ast
from pathlib import Path

import masks

ROOT = Path(masks.__file__).parent


def _module_name(path):
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path, name):
    """Modules of the masks package that ``path`` imports anywhere in its body."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            found.add(base)
            # `from . import layout` names a module, not an attribute
            found.update(f"{base}.{a.name}" for a in node.names)
    return {m for m in found if m == "masks" or m.startswith("masks.")}


def _graph():
    modules = {_module_name(p): p for p in ROOT.rglob("*.py")}
    return {name: sorted(_imports(p, name) & set(modules) - {name}) for name, p in modules.items()}


def _cycle(graph):
    """One import cycle as a list of modules, or None (depth-first search, three colours)."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in graph[node]:
            if state.get(nxt) == "open":
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        state[node] = "done"
        stack.pop()
        return None

    for node in graph:
        if node not in state and (found := visit(node)):
            return found
    return None


def test_cycle_finder_finds_a_planted_cycle():
    assert _cycle({"a": ["b"], "b": ["c"], "c": ["a"], "d": []}) == ["a", "b", "c", "a"]
    assert _cycle({"a": ["b"], "b": [], "c": ["a", "b"]}) is None


def test_masks_modules_import_without_cycles():
    graph = _graph()
    assert "masks.gds" in graph and "masks.layout" in graph["masks.gds"]  # the walker sees imports
    assert _cycle(graph) is None, " -> ".join(_cycle(graph))
