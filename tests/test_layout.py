"""The package's shape (issue #19): small modules, no import cycles, the CLI on top."""

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "cm3d"
MAX_LINES = 700


def _module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, name: str, modules: set[str]) -> set[str]:
    """cm3d modules imported at module level (function-level, lazy imports are not edges)."""
    tree = ast.parse(path.read_text())
    pkg = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in tree.body:
        if isinstance(node, ast.If):  # `if TYPE_CHECKING:` blocks are not imports at run time
            continue
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            out.add(base)
            out |= {f"{base}.{a.name}" for a in node.names}
    return {m for m in out if m in modules and m != name}


def _graph():
    files = {_module_name(p): p for p in PKG.rglob("*.py")}
    return {m: _imports(p, m, set(files)) for m, p in files.items()}, files


def test_no_module_over_700_lines():
    _, files = _graph()
    long = {m: n for m, p in files.items() if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines: {long}"


def test_no_import_cycles():
    graph, _ = _graph()
    # a module importing from its own parent package (``from cm3d.memory import bank`` inside
    # cm3d/memory/) names a package that is already initialising: not an edge
    def edges(m):
        return {d for d in graph[m] if not m.startswith(d + ".")}

    state, cycles = {}, []

    def visit(m, stack):
        state[m] = 1
        stack.append(m)
        for d in edges(m):
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d):] + [d])
            elif d not in state:
                visit(d, stack)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_library_never_imports_the_cli():
    graph, _ = _graph()
    users = sorted(m for m, deps in graph.items() if "cm3d.cli" in deps)
    assert not users, f"the library imports the CLI: {users}"
