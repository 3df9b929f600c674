"""The package layout: subpackages import downwards only, no module import cycles, files of a
size one can hold in one's head, and a small public top level."""
import ast
from pathlib import Path

import ams_torch as at

ROOT = Path(__file__).resolve().parents[1] / "ams_torch"

#: what each subpackage may import (besides itself)
ALLOWED = {
    "geometry": set(),
    "native": set(),
    "solver": {"native"},
    "stages": {"geometry", "solver", "native"},
    "grooms": {"geometry"},
    "sim": {"stages", "solver", "native", "geometry"},
    "apps": {"sim", "stages", "solver", "native", "geometry", "grooms", "top"},
}


def _modules():
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield ".".join(parts), path


def _imports(name: str, path: Path) -> set:
    """Every ams_torch module a file imports, at any level (module or function scope)."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):  # imports only for type checkers do not run
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            node.body = []
    out = set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("ams_torch")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.startswith("ams_torch"):
                out.add(mod)
                out |= {f"{mod}.{a.name}" for a in node.names}
    return out


def _group(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in ALLOWED else "top"


def test_subpackages_import_downwards_only():
    known = {m for m, _ in _modules()}
    bad = []
    for name, path in _modules():
        src = _group(name)
        if src == "top":
            continue
        for target in _imports(name, path):
            if target not in known:
                continue  # a name imported from a module, not a module
            dst = _group(target)
            if dst != src and dst not in ALLOWED[src]:
                bad.append(f"{name} -> {target}")
    assert not bad, "imports against the layering:\n" + "\n".join(bad)


def test_no_module_import_cycles():
    known = {m for m, _ in _modules()}
    graph = {name: {t for t in _imports(name, path) if t in known and t != name
                    and not name.startswith(t + ".")}  # a module may import its own package's __init__
             for name, path in _modules()}
    index, low, stack, on_stack, cycles, counter = {}, {}, [], set(), [], [0]

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def test_no_file_is_too_long():
    long = [f"{p.relative_to(ROOT.parent)} ({n} lines)" for p in ROOT.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 560]
    assert not long, long


def test_the_top_level_is_small():
    names = [n for n in at.__all__ if n not in ("apps", "geometry", "grooms", "sim", "solver", "stages",
                                                "__version__")]
    assert len(names) <= 13, names
    assert callable(at.native_status) and "cpu" in at.native_status()
